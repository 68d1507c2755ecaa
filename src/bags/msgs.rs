//! `sensor_msgs/Image` and `sensor_msgs/CompressedImage` from a bag's message bytes: CDR
//! (rosbag2) through `cdr-encoding`, ROS 1 serialisation through a little-endian reader (the
//! `rosbag` crate hands messages over as bytes).
use serde::Deserialize;

/// Which kind of image message a topic carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageKind {
    Raw,
    Compressed,
}

impl ImageKind {
    /// From a message type name, ROS 1 (`sensor_msgs/Image`) or ROS 2 (`sensor_msgs/msg/Image`).
    pub fn of(msg_type: &str) -> Option<Self> {
        match msg_type.replace("/msg/", "/").as_str() {
            "sensor_msgs/Image" => Some(Self::Raw),
            "sensor_msgs/CompressedImage" => Some(Self::Compressed),
            _ => None,
        }
    }
}

/// How a topic's messages are serialised.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wire {
    Cdr,
    Ros1,
}

/// The fields of `sensor_msgs/Image` loopd uses.
#[derive(Debug)]
pub struct RawImage<'a> {
    pub stamp: f64,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub big_endian: bool,
    pub step: u32,
    pub data: &'a [u8],
}

#[derive(Debug)]
pub struct CompressedImage<'a> {
    pub stamp: f64,
    pub format: String,
    pub data: &'a [u8],
}

#[derive(Deserialize)]
pub(super) struct Time {
    pub(super) sec: i32,
    pub(super) nanosec: u32,
}

#[derive(Deserialize)]
struct Header {
    stamp: Time,
    #[allow(dead_code)] // Read to move past it; loopd has no use for the camera frame name.
    frame_id: String,
}

#[derive(Deserialize)]
struct CdrImage<'a> {
    header: Header,
    height: u32,
    width: u32,
    encoding: String,
    is_bigendian: u8,
    step: u32,
    data: &'a [u8],
}

#[derive(Deserialize)]
struct CdrCompressed<'a> {
    header: Header,
    format: String,
    data: &'a [u8],
}

pub(super) fn seconds(sec: i64, nanosec: u32) -> f64 {
    sec as f64 + nanosec as f64 * 1e-9
}

/// CDR's 4-byte encapsulation header says the byte order of what follows.
pub(super) fn cdr<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, String> {
    let (head, body) = bytes.split_at_checked(4).ok_or("shorter than its CDR header")?;
    let value = match head[1] {
        0 => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        1 => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body),
        other => return Err(format!("unknown CDR representation {other} (plain CDR expected)")),
    };
    value.map(|(v, _)| v).map_err(|e| format!("not a valid CDR message: {e}"))
}

/// ROS 1 serialisation: little-endian, no padding, strings and arrays prefixed by a u32 length.
pub(super) struct Ros1<'a>(pub(super) &'a [u8]);

impl<'a> Ros1<'a> {
    fn bytes(&mut self, n: usize) -> Result<&'a [u8], String> {
        let (head, rest) = self.0.split_at_checked(n).ok_or("message ends early")?;
        self.0 = rest;
        Ok(head)
    }
    pub(super) fn f64(&mut self) -> Result<f64, String> {
        let b = self.bytes(8)?;
        Ok(f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
    }
    pub(super) fn u32(&mut self) -> Result<u32, String> {
        let b = self.bytes(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u8(&mut self) -> Result<u8, String> {
        Ok(self.bytes(1)?[0])
    }
    fn array(&mut self) -> Result<&'a [u8], String> {
        let n = self.u32()? as usize;
        self.bytes(n)
    }
    pub(super) fn string(&mut self) -> Result<String, String> {
        String::from_utf8(self.array()?.to_vec()).map_err(|_| "a string field is not UTF-8".to_string())
    }
    /// std_msgs/Header: seq, stamp (secs, nsecs), frame_id. Returns the stamp.
    pub(super) fn header(&mut self) -> Result<f64, String> {
        Ok(self.header_frame()?.0)
    }
    /// std_msgs/Header's stamp and frame_id.
    pub(super) fn header_frame(&mut self) -> Result<(f64, String), String> {
        self.u32()?;
        let (sec, nsec) = (self.u32()?, self.u32()?);
        let frame = self.string()?;
        Ok((seconds(sec as i64, nsec), frame))
    }
}

pub fn raw_image(wire: Wire, bytes: &[u8]) -> Result<RawImage<'_>, String> {
    match wire {
        Wire::Cdr => {
            let m: CdrImage = cdr(bytes)?;
            Ok(RawImage {
                stamp: seconds(m.header.stamp.sec as i64, m.header.stamp.nanosec),
                height: m.height,
                width: m.width,
                encoding: m.encoding,
                big_endian: m.is_bigendian != 0,
                step: m.step,
                data: m.data,
            })
        }
        Wire::Ros1 => {
            let mut r = Ros1(bytes);
            let stamp = r.header()?;
            let (height, width, encoding) = (r.u32()?, r.u32()?, r.string()?);
            let (big_endian, step, data) = (r.u8()? != 0, r.u32()?, r.array()?);
            Ok(RawImage { stamp, height, width, encoding, big_endian, step, data })
        }
    }
}

pub fn compressed_image(wire: Wire, bytes: &[u8]) -> Result<CompressedImage<'_>, String> {
    match wire {
        Wire::Cdr => {
            let m: CdrCompressed = cdr(bytes)?;
            Ok(CompressedImage {
                stamp: seconds(m.header.stamp.sec as i64, m.header.stamp.nanosec),
                format: m.format,
                data: m.data,
            })
        }
        Wire::Ros1 => {
            let mut r = Ros1(bytes);
            let stamp = r.header()?;
            let (format, data) = (r.string()?, r.array()?);
            Ok(CompressedImage { stamp, format, data })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros1_compressed_image_round_trip() {
        let mut m = Vec::new();
        for v in [7u32, 12, 500_000_000] {
            m.extend(v.to_le_bytes());
        }
        for s in [&b"cam"[..], b"jpeg", b"\xff\xd8\xff\xd9"] {
            m.extend((s.len() as u32).to_le_bytes());
            m.extend(s);
        }
        let c = compressed_image(Wire::Ros1, &m).unwrap();
        assert_eq!((c.stamp, c.format.as_str(), c.data), (12.5, "jpeg", &b"\xff\xd8\xff\xd9"[..]));
        assert!(compressed_image(Wire::Ros1, &m[..m.len() - 1]).is_err(), "a cut message is an error");
    }

    #[test]
    fn types() {
        assert_eq!(ImageKind::of("sensor_msgs/msg/Image"), Some(ImageKind::Raw));
        assert_eq!(ImageKind::of("sensor_msgs/CompressedImage"), Some(ImageKind::Compressed));
        assert_eq!(ImageKind::of("sensor_msgs/msg/Imu"), None);
    }
}
