//! Dot products of one f32 query with many stored rows, f16 or f32.
//!
//! Exact search is memory-bound: f16 rows halve the bytes streamed per query, which is
//! where the single-query speed comes from. AVX2+FMA+F16C when the CPU has them
//! (checked at run time), plain Rust otherwise.
use half::f16;

/// `out[i] = dot(q, rows[i*dim..])` for f16 rows stored as raw bits.
pub fn dots_f16(q: &[f32], rows: &[u16], out: &mut [f32]) {
    let dim = q.len();
    debug_assert_eq!(rows.len(), out.len() * dim);
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8)
        && std::is_x86_feature_detected!("avx2")
        && std::is_x86_feature_detected!("fma")
        && std::is_x86_feature_detected!("f16c")
    {
        // SAFETY: the features were just detected; lengths are checked by the chunking below.
        unsafe { x86::dots_f16(q, rows, out) };
        return;
    }
    for (o, row) in out.iter_mut().zip(rows.chunks_exact(dim)) {
        *o = q.iter().zip(row).map(|(a, &b)| a * f16::from_bits(b).to_f32()).sum();
    }
}

/// `out[i] = dot(q, rows[i*dim..])` for f32 rows.
pub fn dots_f32(q: &[f32], rows: &[f32], out: &mut [f32]) {
    let dim = q.len();
    debug_assert_eq!(rows.len(), out.len() * dim);
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8) && std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: as above.
        unsafe { x86::dots_f32(q, rows, out) };
        return;
    }
    for (o, row) in out.iter_mut().zip(rows.chunks_exact(dim)) {
        *o = q.iter().zip(row).map(|(a, b)| a * b).sum();
    }
}

/// f16 bits to f32, vectorised with F16C where available.
pub fn f16_to_f32(src: &[u16], dst: &mut [f32]) {
    debug_assert_eq!(src.len(), dst.len());
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("f16c") {
        // SAFETY: features detected; equal lengths checked by the caller contract above.
        unsafe { x86::f16_to_f32(src, dst) };
        return;
    }
    for (d, &s) in dst.iter_mut().zip(src) {
        *d = f16::from_bits(s).to_f32();
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    #[inline(always)]
    unsafe fn hsum(v: __m256) -> f32 {
        let lo = _mm256_castps256_ps128(v);
        let hi = _mm256_extractf128_ps(v, 1);
        let s = _mm_add_ps(lo, hi);
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        let s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
        _mm_cvtss_f32(s)
    }

    /// Two rows at a time share each query load; four accumulators per row hide FMA latency.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub unsafe fn dots_f16(q: &[f32], rows: &[u16], out: &mut [f32]) {
        let dim = q.len();
        let qp = q.as_ptr();
        let n = out.len();
        let mut i = 0;
        while i + 2 <= n {
            let (r0, r1) = (rows.as_ptr().add(i * dim), rows.as_ptr().add((i + 1) * dim));
            let (mut a0, mut a1, mut b0, mut b1) =
                (_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps());
            let mut j = 0;
            while j + 16 <= dim {
                let q0 = _mm256_loadu_ps(qp.add(j));
                let q1 = _mm256_loadu_ps(qp.add(j + 8));
                a0 = _mm256_fmadd_ps(q0, _mm256_cvtph_ps(_mm_loadu_si128(r0.add(j) as *const __m128i)), a0);
                a1 = _mm256_fmadd_ps(q1, _mm256_cvtph_ps(_mm_loadu_si128(r0.add(j + 8) as *const __m128i)), a1);
                b0 = _mm256_fmadd_ps(q0, _mm256_cvtph_ps(_mm_loadu_si128(r1.add(j) as *const __m128i)), b0);
                b1 = _mm256_fmadd_ps(q1, _mm256_cvtph_ps(_mm_loadu_si128(r1.add(j + 8) as *const __m128i)), b1);
                j += 16;
            }
            while j < dim {
                let q0 = _mm256_loadu_ps(qp.add(j));
                a0 = _mm256_fmadd_ps(q0, _mm256_cvtph_ps(_mm_loadu_si128(r0.add(j) as *const __m128i)), a0);
                b0 = _mm256_fmadd_ps(q0, _mm256_cvtph_ps(_mm_loadu_si128(r1.add(j) as *const __m128i)), b0);
                j += 8;
            }
            out[i] = hsum(_mm256_add_ps(a0, a1));
            out[i + 1] = hsum(_mm256_add_ps(b0, b1));
            i += 2;
        }
        if i < n {
            let r0 = rows.as_ptr().add(i * dim);
            let mut a0 = _mm256_setzero_ps();
            let mut j = 0;
            while j < dim {
                a0 = _mm256_fmadd_ps(
                    _mm256_loadu_ps(qp.add(j)),
                    _mm256_cvtph_ps(_mm_loadu_si128(r0.add(j) as *const __m128i)),
                    a0,
                );
                j += 8;
            }
            out[i] = hsum(a0);
        }
    }

    #[target_feature(enable = "avx2,f16c")]
    pub unsafe fn f16_to_f32(src: &[u16], dst: &mut [f32]) {
        let n = src.len().min(dst.len());
        let mut i = 0;
        while i + 8 <= n {
            _mm256_storeu_ps(
                dst.as_mut_ptr().add(i),
                _mm256_cvtph_ps(_mm_loadu_si128(src.as_ptr().add(i) as *const __m128i)),
            );
            i += 8;
        }
        for j in i..n {
            dst[j] = half::f16::from_bits(src[j]).to_f32();
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn dots_f32(q: &[f32], rows: &[f32], out: &mut [f32]) {
        let dim = q.len();
        let qp = q.as_ptr();
        for (i, o) in out.iter_mut().enumerate() {
            let r = rows.as_ptr().add(i * dim);
            let (mut a0, mut a1) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            let mut j = 0;
            while j + 16 <= dim {
                a0 = _mm256_fmadd_ps(_mm256_loadu_ps(qp.add(j)), _mm256_loadu_ps(r.add(j)), a0);
                a1 = _mm256_fmadd_ps(_mm256_loadu_ps(qp.add(j + 8)), _mm256_loadu_ps(r.add(j + 8)), a1);
                j += 16;
            }
            while j < dim {
                a0 = _mm256_fmadd_ps(_mm256_loadu_ps(qp.add(j)), _mm256_loadu_ps(r.add(j)), a0);
                j += 8;
            }
            *o = hsum(_mm256_add_ps(a0, a1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simd_matches_scalar() {
        for dim in [8usize, 24, 256, 2048] {
            let n = 7;
            let q: Vec<f32> = (0..dim).map(|i| ((i * 7 % 13) as f32 - 6.0) / 10.0).collect();
            let rows32: Vec<f32> = (0..n * dim).map(|i| ((i * 5 % 11) as f32 - 5.0) / 8.0).collect();
            let rows16: Vec<u16> = rows32.iter().map(|&v| f16::from_f32(v).to_bits()).collect();
            let (mut o16, mut o32) = (vec![0.0; n], vec![0.0; n]);
            dots_f16(&q, &rows16, &mut o16);
            dots_f32(&q, &rows32, &mut o32);
            for r in 0..n {
                let exact: f32 = (0..dim).map(|j| q[j] * rows32[r * dim + j]).sum();
                assert!((o32[r] - exact).abs() < 1e-3, "f32 dim {dim} row {r}");
                assert!((o16[r] - exact).abs() < 1e-3 * dim as f32 / 8.0, "f16 dim {dim} row {r}");
            }
        }
    }
}
