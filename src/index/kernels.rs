//! Dot products of one f32 query with many stored rows, f16 or f32.
//!
//! Exact search is memory-bound: f16 rows halve the bytes streamed per query, which is
//! where the single-query speed comes from. AVX2+FMA+F16C when the CPU has them
//! (checked at run time), plain Rust otherwise.
use half::f16;

/// The shape every single-query kernel relies on: `out.len()` rows of `q.len()` values.
/// Checked in release builds too: the SIMD kernels read `rows` through raw pointers.
fn check_shape(dim: usize, rows: usize, out: usize) {
    assert!(
        dim > 0 && out.checked_mul(dim) == Some(rows),
        "dot kernel shape: {rows} row values for {out} outputs of dimension {dim}"
    );
}

/// `out[i] = dot(q, rows[i*dim..])` for f16 rows stored as raw bits.
///
/// # Panics
/// If `rows.len() != out.len() * q.len()` or `q` is empty.
pub(crate) fn dots_f16(q: &[f32], rows: &[u16], out: &mut [f32]) {
    let dim = q.len();
    check_shape(dim, rows.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8)
        && std::is_x86_feature_detected!("avx2")
        && std::is_x86_feature_detected!("fma")
        && std::is_x86_feature_detected!("f16c")
    {
        // SAFETY: AVX2/FMA/F16C were just detected; check_shape proved rows.len() == out.len() * dim
        // and dim is a multiple of 8, which is the kernel's whole contract.
        unsafe { x86::dots_f16(q, rows, out) };
        return;
    }
    for (o, row) in out.iter_mut().zip(rows.chunks_exact(dim)) {
        *o = q.iter().zip(row).map(|(a, &b)| a * f16::from_bits(b).to_f32()).sum();
    }
}

/// `out[i] = dot(q, rows[i*dim..])` for f32 rows.
///
/// # Panics
/// If `rows.len() != out.len() * q.len()` or `q` is empty.
pub(crate) fn dots_f32(q: &[f32], rows: &[f32], out: &mut [f32]) {
    let dim = q.len();
    check_shape(dim, rows.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8) && std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: AVX2/FMA were just detected; check_shape proved the lengths, dim is a multiple of 8.
        unsafe { x86::dots_f32(q, rows, out) };
        return;
    }
    for (o, row) in out.iter_mut().zip(rows.chunks_exact(dim)) {
        *o = q.iter().zip(row).map(|(a, b)| a * b).sum();
    }
}

/// The shape the batch kernels rely on: whole rows and queries of `dim` values, one output each pair.
fn check_many_shape(dim: usize, queries: usize, rows: usize, out: usize) {
    let ok = dim > 0
        && queries.is_multiple_of(dim)
        && rows.is_multiple_of(dim)
        && (queries / dim).checked_mul(rows / dim) == Some(out);
    assert!(ok, "batch dot kernel shape: {queries} query values, {rows} row values, {out} outputs, dimension {dim}");
}

/// `out[r * nq + q] = dot(rows[r], queries[q])`: a block of stored rows against `nq` queries
/// (both row-major, `dim` wide). Register-blocked so each loaded row value serves four queries:
/// with tens of queries this is compute-bound, not memory-bound.
///
/// # Panics
/// If the lengths are not whole rows/queries of `dim` values with one output per pair.
pub(crate) fn dots_many_f16(queries: &[f32], rows: &[u16], dim: usize, out: &mut [f32]) {
    check_many_shape(dim, queries.len(), rows.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8)
        && std::is_x86_feature_detected!("avx2")
        && std::is_x86_feature_detected!("fma")
        && std::is_x86_feature_detected!("f16c")
    {
        // SAFETY: AVX2/FMA/F16C detected; check_many_shape proved whole rows/queries and the
        // output length, dim is a multiple of 8 (the kernel asserts the same again).
        unsafe { x86::dots_many(queries, rows, dim, out) };
        return;
    }
    dots_many_fallback(queries, rows.len() / dim, dim, out, |q, tmp| dots_f16(q, rows, tmp));
}

/// As [`dots_many_f16`] for f32 rows.
pub(crate) fn dots_many_f32(queries: &[f32], rows: &[f32], dim: usize, out: &mut [f32]) {
    check_many_shape(dim, queries.len(), rows.len(), out.len());
    #[cfg(target_arch = "x86_64")]
    if dim.is_multiple_of(8) && std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: AVX2/FMA detected; shapes proved by check_many_shape, dim a multiple of 8.
        unsafe { x86::dots_many(queries, rows, dim, out) };
        return;
    }
    dots_many_fallback(queries, rows.len() / dim, dim, out, |q, tmp| dots_f32(q, rows, tmp));
}

/// One query at a time, scattered into the rows x queries layout.
fn dots_many_fallback(queries: &[f32], nr: usize, dim: usize, out: &mut [f32], dots: impl Fn(&[f32], &mut [f32])) {
    let nq = queries.len() / dim.max(1);
    assert_eq!(out.len(), nr * nq, "output is rows x queries");
    let mut tmp = vec![0f32; nr];
    for (qi, q) in queries.chunks_exact(dim).enumerate() {
        dots(q, &mut tmp);
        for (r, &v) in tmp.iter().enumerate() {
            out[r * nq + qi] = v;
        }
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
    ///
    /// # Safety
    /// The CPU has AVX2, FMA and F16C; `q.len()` is a non-zero multiple of 8 and
    /// `rows.len() == out.len() * q.len()` (rows are read through raw pointers).
    #[target_feature(enable = "avx2,fma,f16c")]
    pub(super) unsafe fn dots_f16(q: &[f32], rows: &[u16], out: &mut [f32]) {
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

    /// A stored value type the batch kernel can widen to eight f32 lanes.
    pub trait Lanes: Copy {
        /// # Safety
        /// `p..p+8` must be readable and the CPU must have AVX2/F16C.
        unsafe fn load8(p: *const Self) -> __m256;
    }
    impl Lanes for u16 {
        #[inline(always)]
        unsafe fn load8(p: *const u16) -> __m256 {
            _mm256_cvtph_ps(_mm_loadu_si128(p as *const __m128i))
        }
    }
    impl Lanes for f32 {
        #[inline(always)]
        unsafe fn load8(p: *const f32) -> __m256 {
            _mm256_loadu_ps(p)
        }
    }

    /// Query values per K-slice: four queries' slices (16 KB) stay in L1 while rows stream from L2.
    const KC: usize = 1024;

    /// # Safety
    /// The CPU has AVX2, FMA and F16C (shapes are asserted here before any pointer arithmetic).
    #[target_feature(enable = "avx2,fma,f16c")]
    pub(super) unsafe fn dots_many<T: Lanes>(queries: &[f32], rows: &[T], dim: usize, out: &mut [f32]) {
        let (nq, nr) = (queries.len() / dim, rows.len() / dim);
        assert!(dim.is_multiple_of(8) && queries.len() == nq * dim && rows.len() == nr * dim);
        assert_eq!(out.len(), nr * nq, "output is rows x queries");
        out.fill(0.0);
        let mut k0 = 0;
        while k0 < dim {
            let kl = KC.min(dim - k0);
            let mut q0 = 0;
            while q0 < nq {
                let qn = (nq - q0).min(TQ);
                let mut r0 = 0;
                while r0 < nr {
                    let rn = (nr - r0).min(TR);
                    let qp = queries.as_ptr().add(q0 * dim + k0);
                    let rp = rows.as_ptr().add(r0 * dim + k0);
                    let op = out.as_mut_ptr().add(r0 * nq + q0);
                    tile_dispatch(rn, qn, qp, rp, dim, kl, op, nq);
                    r0 += rn;
                }
                q0 += qn;
            }
            k0 += kl;
        }
    }

    /// Rows and queries per register tile (3x4: 12 accumulators, 3 widened rows, 1 query).
    const TR: usize = 3;
    const TQ: usize = 4;

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    unsafe fn tile_dispatch<T: Lanes>(
        rn: usize,
        qn: usize,
        qp: *const f32,
        rp: *const T,
        dim: usize,
        kl: usize,
        op: *mut f32,
        nq: usize,
    ) {
        macro_rules! go { ($($r:literal $q:literal),*) => { match (rn, qn) { $(($r, $q) => tile::<T, $r, $q>(qp, rp, dim, kl, op, nq),)* _ => unreachable!() } } }
        go!(1 1, 1 2, 1 3, 1 4, 2 1, 2 2, 2 3, 2 4, 3 1, 3 2, 3 3, 3 4)
    }

    /// # Safety
    /// `rows + r*dim + j` and `q + qi*dim + j` are readable for j < len (len a multiple of 8),
    /// r < R, qi < Q, and `out + r*nq + qi` is writable: `dots_many`'s loops guarantee it.
    ///
    /// R rows x Q queries over `len` values: R*Q accumulators (12 of the 16 ymm registers at 3x4),
    /// each row value widened once and each query value loaded once per step.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // qi and r index both axes of the register tile
    unsafe fn tile<T: Lanes, const R: usize, const Q: usize>(
        q: *const f32,
        rows: *const T,
        dim: usize,
        len: usize,
        out: *mut f32,
        nq: usize,
    ) {
        let mut acc = [[_mm256_setzero_ps(); Q]; R];
        let mut j = 0;
        while j < len {
            let mut rv = [_mm256_setzero_ps(); R];
            for (r, v) in rv.iter_mut().enumerate() {
                *v = T::load8(rows.add(r * dim + j));
            }
            for qi in 0..Q {
                let qv = _mm256_loadu_ps(q.add(qi * dim + j));
                for r in 0..R {
                    acc[r][qi] = _mm256_fmadd_ps(rv[r], qv, acc[r][qi]);
                }
            }
            j += 8;
        }
        for (r, row) in acc.iter().enumerate() {
            if Q == 4 {
                // Four sums at once: three horizontal adds, then the two 128-bit halves.
                let t = _mm256_hadd_ps(_mm256_hadd_ps(row[0], row[1]), _mm256_hadd_ps(row[2], row[3]));
                let s = _mm_add_ps(_mm256_castps256_ps128(t), _mm256_extractf128_ps(t, 1));
                let o = out.add(r * nq);
                _mm_storeu_ps(o, _mm_add_ps(_mm_loadu_ps(o), s));
                continue;
            }
            for (qi, a) in row.iter().enumerate() {
                *out.add(r * nq + qi) += hsum(*a);
            }
        }
    }

    /// # Safety
    /// The CPU has AVX2 and FMA; `q.len()` is a non-zero multiple of 8 and
    /// `rows.len() == out.len() * q.len()` (rows are read through raw pointers).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn dots_f32(q: &[f32], rows: &[f32], out: &mut [f32]) {
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

    /// Mismatched shapes stop before any read, in release builds as well.
    #[test]
    fn wrong_shapes_are_refused_not_read() {
        let q = vec![0.5f32; 16];
        let short16 = vec![0u16; 16 * 3 - 8];
        let short32 = vec![0f32; 16 * 3 - 8];
        let caught = |f: &(dyn Fn() + std::panic::RefUnwindSafe)| std::panic::catch_unwind(f).is_err();
        assert!(caught(&|| dots_f16(&q, &short16, &mut [0f32; 3])));
        assert!(caught(&|| dots_f32(&q, &short32, &mut [0f32; 3])));
        assert!(caught(&|| dots_f32(&[], &[], &mut [0f32; 3])));
        assert!(caught(&|| dots_many_f16(&q, &short16, 16, &mut [0f32; 3])));
        assert!(caught(&|| dots_many_f32(&q[..8], &short32, 16, &mut [0f32; 3])));
        // The right shapes still work.
        let mut out = [0f32; 3];
        dots_f32(&q, &[1f32; 48], &mut out);
        assert_eq!(out, [8.0; 3]);
    }

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

    /// Every tile shape (rows mod 3, queries mod 4) and a dim spanning several K-slices.
    #[test]
    fn batch_kernel_matches_single_kernel() {
        for (dim, nr, nq) in [(2048usize, 13usize, 7usize), (256, 5, 64), (8, 1, 1), (520, 3, 4), (12, 4, 3)] {
            let queries: Vec<f32> = (0..nq * dim).map(|i| ((i * 7 % 13) as f32 - 6.0) / 10.0).collect();
            let rows32: Vec<f32> = (0..nr * dim).map(|i| ((i * 5 % 11) as f32 - 5.0) / 8.0).collect();
            let rows16: Vec<u16> = rows32.iter().map(|&v| f16::from_f32(v).to_bits()).collect();
            let (mut m16, mut m32) = (vec![f32::NAN; nr * nq], vec![f32::NAN; nr * nq]);
            dots_many_f16(&queries, &rows16, dim, &mut m16);
            dots_many_f32(&queries, &rows32, dim, &mut m32);
            for (qi, q) in queries.chunks_exact(dim).enumerate() {
                let (mut s16, mut s32) = (vec![0.0; nr], vec![0.0; nr]);
                dots_f16(q, &rows16, &mut s16);
                dots_f32(q, &rows32, &mut s32);
                for r in 0..nr {
                    let tol = 1e-4 * (1.0 + s32[r].abs());
                    assert!((m32[r * nq + qi] - s32[r]).abs() < tol, "f32 dim {dim} row {r} query {qi}");
                    assert!((m16[r * nq + qi] - s16[r]).abs() < tol, "f16 dim {dim} row {r} query {qi}");
                }
            }
        }
    }
}
