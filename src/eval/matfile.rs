//! Just enough of the MATLAB v5 MAT-file format to read a 2-d ground-truth matrix:
//! compressed or plain elements, numeric and logical classes, and sparse matrices.
use anyhow::{bail, Context, Result};
use std::io::Read;

const MI_INT8: u32 = 1;
const MI_UINT8: u32 = 2;
const MI_INT16: u32 = 3;
const MI_UINT16: u32 = 4;
const MI_INT32: u32 = 5;
const MI_UINT32: u32 = 6;
const MI_SINGLE: u32 = 7;
const MI_DOUBLE: u32 = 9;
const MI_INT64: u32 = 12;
const MI_UINT64: u32 = 13;
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;
const MX_SPARSE: u32 = 5;

/// A named 2-d matrix, as the (row, column) positions of its non-zero entries.
pub struct MatMatrix {
    pub name: String,
    pub rows: usize,
    pub cols: usize,
    pub nonzero: Vec<(usize, usize)>,
}

struct Cursor<'a> {
    b: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn u32(&mut self) -> Result<u32> {
        let v = self.b.get(self.pos..self.pos + 4).context("MAT file ends early")?;
        self.pos += 4;
        Ok(u32::from_le_bytes([v[0], v[1], v[2], v[3]]))
    }

    /// One data element: (type, payload). Handles the "small element" 8-byte form.
    fn element(&mut self) -> Result<(u32, &'a [u8])> {
        let tag = self.u32()?;
        if tag >> 16 != 0 {
            let (ty, n) = (tag & 0xffff, (tag >> 16) as usize);
            let data = self.b.get(self.pos..self.pos + n).context("MAT small element ends early")?;
            self.pos += 4;
            return Ok((ty, data));
        }
        let n = self.u32()? as usize;
        let data = self.b.get(self.pos..self.pos + n).context("MAT element ends early")?;
        // Elements are padded to 8 bytes (compressed ones are not).
        self.pos += if tag == MI_COMPRESSED { n } else { n.div_ceil(8) * 8 };
        Ok((tag, data))
    }
}

fn numbers(ty: u32, d: &[u8]) -> Result<Vec<f64>> {
    macro_rules! conv {
        ($t:ty, $n:expr) => {
            d.chunks_exact($n).map(|c| <$t>::from_le_bytes(c.try_into().expect("chunk size")) as f64).collect()
        };
    }
    Ok(match ty {
        MI_INT8 => d.iter().map(|&v| v as i8 as f64).collect(),
        MI_UINT8 => d.iter().map(|&v| v as f64).collect(),
        MI_INT16 => conv!(i16, 2),
        MI_UINT16 => conv!(u16, 2),
        MI_INT32 => conv!(i32, 4),
        MI_UINT32 => conv!(u32, 4),
        MI_SINGLE => conv!(f32, 4),
        MI_DOUBLE => conv!(f64, 8),
        MI_INT64 => conv!(i64, 8),
        MI_UINT64 => conv!(u64, 8),
        _ => bail!("unsupported MAT data type {ty}"),
    })
}

fn matrix(payload: &[u8]) -> Result<MatMatrix> {
    let mut c = Cursor { b: payload, pos: 0 };
    let (_, flags) = c.element()?;
    let class = u32::from_le_bytes(flags.get(..4).context("array flags")?.try_into()?) & 0xff;
    let (_, dims) = c.element()?;
    let dims = numbers(MI_INT32, dims)?;
    if dims.len() != 2 {
        bail!("expected a 2-d matrix, got {} dimensions", dims.len());
    }
    let (rows, cols) = (dims[0] as usize, dims[1] as usize);
    let (_, name) = c.element()?;
    let name = String::from_utf8_lossy(name).to_string();
    let mut nonzero = Vec::new();
    if class == MX_SPARSE {
        let (t, ir) = c.element()?;
        let ir = numbers(t, ir)?;
        let (t, jc) = c.element()?;
        let jc = numbers(t, jc)?;
        let (t, pr) = c.element()?;
        let pr = numbers(t, pr)?;
        for col in 0..cols {
            let (start, end) = (jc[col] as usize, jc[col + 1] as usize);
            for (k, &row) in ir.iter().enumerate().take(end).skip(start) {
                if pr.get(k).copied().unwrap_or(1.0) != 0.0 {
                    nonzero.push((row as usize, col));
                }
            }
        }
    } else {
        let (t, data) = c.element()?;
        let values = numbers(t, data)?;
        if values.len() != rows * cols {
            bail!("matrix {name}: {} values for {rows}x{cols}", values.len());
        }
        // Column-major.
        for (k, &v) in values.iter().enumerate() {
            if v != 0.0 {
                nonzero.push((k % rows, k / rows));
            }
        }
    }
    Ok(MatMatrix { name, rows, cols, nonzero })
}

/// The first matrix in a MAT-file.
pub fn read_matrix(bytes: &[u8]) -> Result<MatMatrix> {
    if bytes.len() < 128 || &bytes[126..128] != b"IM" {
        bail!("not a little-endian MATLAB v5 MAT-file");
    }
    let mut c = Cursor { b: bytes, pos: 128 };
    while c.pos < bytes.len() {
        let (ty, data) = c.element()?;
        match ty {
            MI_MATRIX => return matrix(data),
            MI_COMPRESSED => {
                let mut inner = Vec::new();
                flate2::read::ZlibDecoder::new(data).read_to_end(&mut inner).context("inflating MAT element")?;
                let mut ic = Cursor { b: &inner, pos: 0 };
                let (ty, data) = ic.element()?;
                if ty == MI_MATRIX {
                    return matrix(data);
                }
            }
            _ => {}
        }
    }
    bail!("no matrix in MAT-file")
}
