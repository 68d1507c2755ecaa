//! A session's rows mirrored on a libtorch device (the model's GPU): exact scores come from one
//! matrix product and the top candidates are picked on the device, so only a few (score, row)
//! pairs per query cross back to the host.
use tch::{Device, Kind, Tensor};

/// Rows copied to the device, in the session's storage precision; filled lazily from the host rows
/// (the source of truth) right before a search, so inserts and start-up rebuilds stay on the host.
pub struct DeviceRows {
    device: Device,
    kind: Kind,
    dim: usize,
    /// [capacity, dim]; rows past `len` are unused.
    rows: Tensor,
    len: usize,
}

/// Host rows as they are stored in the index.
pub enum HostRows<'a> {
    F16(&'a [u16]),
    F32(&'a [f32]),
}

impl DeviceRows {
    pub fn new(device: Device, half: bool, dim: usize) -> Self {
        let kind = if half { Kind::Half } else { Kind::Float };
        Self { device, kind, dim, rows: Tensor::zeros([0, dim as i64], (kind, device)), len: 0 }
    }

    /// Copies host rows this mirror does not hold yet (one transfer for all of them).
    pub fn sync(&mut self, host: HostRows<'_>) -> Result<(), tch::TchError> {
        let (n, dim) = (
            match host {
                HostRows::F16(v) => v.len(),
                HostRows::F32(v) => v.len(),
            } / self.dim,
            self.dim as i64,
        );
        if n <= self.len {
            return Ok(());
        }
        let add = n - self.len;
        let cap = self.rows.size()[0] as usize;
        if n > cap {
            // Doubling keeps the copies amortised as a map grows one keyframe at a time.
            let grown = Tensor::f_zeros([n.max(cap * 2).max(1024) as i64, dim], (self.kind, self.device))?;
            if self.len > 0 {
                grown.narrow(0, 0, self.len as i64).f_copy_(&self.rows.narrow(0, 0, self.len as i64))?;
            }
            self.rows = grown;
        }
        let range = self.len * self.dim..n * self.dim;
        let src = match host {
            // f16 bits go up as they are: no widening on the host, half the bytes over the bus.
            HostRows::F16(v) => {
                let bytes: Vec<u8> = v[range].iter().flat_map(|b| b.to_le_bytes()).collect();
                Tensor::f_from_data_size(&bytes, &[add as i64, dim], Kind::Half)?
            }
            HostRows::F32(v) => Tensor::f_from_slice(&v[range])?.f_reshape([add as i64, dim])?,
        };
        self.rows.narrow(0, self.len as i64, add as i64).f_copy_(&src.f_to_kind(self.kind)?)?;
        self.len = n;
        Ok(())
    }

    /// The best `fetch` rows of each query (row-major queries, `dim` wide): (score, row), best first.
    pub fn top(&self, queries: &[f32], fetch: usize) -> Result<Vec<Vec<(f32, usize)>>, tch::TchError> {
        let b = queries.len() / self.dim;
        let fetch = fetch.min(self.len);
        if b == 0 || fetch == 0 {
            return Ok(vec![Vec::new(); b]);
        }
        let q = Tensor::f_from_slice(queries)?
            .f_reshape([b as i64, self.dim as i64])?
            .f_to_device(self.device)?
            .f_to_kind(self.kind)?;
        let rows = self.rows.narrow(0, 0, self.len as i64);
        let scores = q.f_matmul(&rows.f_tr()?)?; // [b, len]
        let (values, idx) = scores.f_topk(fetch as i64, 1, true, true)?;
        let values = Vec::<f32>::try_from(values.f_to_kind(Kind::Float)?.f_to_device(Device::Cpu)?.f_flatten(0, -1)?)?;
        let idx = Vec::<i64>::try_from(idx.f_to_device(Device::Cpu)?.f_flatten(0, -1)?)?;
        Ok(values
            .chunks_exact(fetch)
            .zip(idx.chunks_exact(fetch))
            .map(|(v, i)| v.iter().zip(i).map(|(&s, &r)| (s, r as usize)).collect())
            .collect())
    }
}
