//! ROS 1 bags (format 2.0) through the `rosbag` crate. It slices the file at the header's index
//! position and sizes chunk buffers from their headers without checking either, so both are
//! checked here first: a truncated or crafted bag is an error, never a panic or a 4 GiB buffer.
use super::msgs::Wire;
use super::{BagError, Visit};
use rosbag::{ChunkRecord, MessageRecord, RosBag};
use std::collections::HashMap;
use std::io::Write;

pub const MAGIC: &[u8] = b"#ROSBAG V2.0\n";
const OP_BAG_HEADER: u8 = 0x03;
const OP_CHUNK: u8 = 0x05;

fn err(why: impl Into<String>) -> BagError {
    BagError::Corrupt(format!("ROS 1 bag: {}", why.into()))
}

/// A record's header fields and data (ROS 1 bag format 2.0: u32-length-prefixed header of
/// u32-length-prefixed `name=value` fields, then u32-length-prefixed data).
struct Record<'a> {
    fields: Vec<(&'a [u8], &'a [u8])>,
    data_len: usize,
    end: usize,
}

fn u32_at(b: &[u8], at: usize) -> Option<usize> {
    b.get(at..at.checked_add(4)?).map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]) as usize)
}

fn record(b: &[u8], at: usize) -> Result<Record<'_>, BagError> {
    let cut = || err(format!("record at byte {at} runs past the end of the file (truncated?)"));
    let header_len = u32_at(b, at).ok_or_else(cut)?;
    let header = b.get(at + 4..at + 4 + header_len).ok_or_else(cut)?;
    let data_len = u32_at(b, at + 4 + header_len).ok_or_else(cut)?;
    let end = at + 8 + header_len + data_len;
    if end > b.len() {
        return Err(cut());
    }
    let mut fields = Vec::new();
    let mut i = 0;
    while i < header.len() {
        let n = u32_at(header, i).ok_or_else(|| err(format!("bad record header at byte {at}")))?;
        let field = header.get(i + 4..i + 4 + n).ok_or_else(|| err(format!("bad record header at byte {at}")))?;
        let eq = field.iter().position(|&c| c == b'=').ok_or_else(|| err(format!("bad header field at byte {at}")))?;
        fields.push((&field[..eq], &field[eq + 1..]));
        i += 4 + n;
    }
    Ok(Record { fields, data_len, end })
}

impl Record<'_> {
    fn field(&self, name: &str) -> Option<&[u8]> {
        self.fields.iter().find(|(n, _)| *n == name.as_bytes()).map(|(_, v)| *v)
    }
    fn op(&self) -> Option<u8> {
        self.field("op").and_then(|v| v.first().copied())
    }
}

/// Walks the chunk section the way the crate will, refusing what would make it panic or
/// allocate more than `max_chunk_bytes`.
fn check(b: &[u8], max_chunk_bytes: usize) -> Result<(), BagError> {
    let header = record(b, MAGIC.len())?;
    if header.op() != Some(OP_BAG_HEADER) {
        return Err(err("no bag header record after the version line"));
    }
    let index_pos = header
        .field("index_pos")
        .and_then(|v| v.try_into().ok())
        .map(u64::from_le_bytes)
        .ok_or_else(|| err("the bag header has no index position"))?;
    if index_pos == 0 {
        return Err(err("the bag has no index: it was not closed after recording (`rosbag reindex` repairs it)"));
    }
    let index_pos = usize::try_from(index_pos).unwrap_or(usize::MAX);
    if index_pos < header.end || index_pos > b.len() {
        return Err(err(format!("the index is said to start at byte {index_pos} of {} (truncated?)", b.len())));
    }
    let mut at = header.end;
    while at < index_pos {
        let r = record(&b[..index_pos], at)?;
        if r.op() == Some(OP_CHUNK) {
            let size = r.field("size").and_then(|v| u32_at(v, 0)).ok_or_else(|| err("a chunk has no size"))?;
            if size > max_chunk_bytes {
                return Err(err(format!("a chunk of {size} bytes; at most {max_chunk_bytes}")));
            }
            if r.field("compression") == Some(b"none") && size != r.data_len {
                return Err(err(format!("an uncompressed chunk of {} bytes says it holds {size}", r.data_len)));
            }
        }
        at = r.end;
    }
    Ok(())
}

/// Every message in chunk order (the order they were recorded in).
pub fn visit(bytes: &[u8], max_chunk_bytes: usize, visit: &mut Visit) -> Result<(), BagError> {
    check(bytes, max_chunk_bytes)?;
    // The crate reads from a mapped file only.
    let mut file = tempfile::NamedTempFile::new().map_err(|e| BagError::Io(e.to_string()))?;
    file.write_all(bytes).and_then(|_| file.flush()).map_err(|e| BagError::Io(e.to_string()))?;
    let bag = RosBag::new(file.path()).map_err(|e| err(e.to_string()))?;
    let mut topics: HashMap<u32, (String, String)> = HashMap::new();
    for record in bag.chunk_records() {
        let ChunkRecord::Chunk(chunk) = record.map_err(|e| err(e.to_string()))? else { continue };
        for m in chunk.messages() {
            match m.map_err(|e| err(e.to_string()))? {
                MessageRecord::Connection(c) => {
                    topics.insert(c.id, (c.topic.to_string(), c.tp.to_string()));
                }
                MessageRecord::MessageData(d) => {
                    let (topic, tp) = topics
                        .get(&d.conn_id)
                        .ok_or_else(|| err(format!("a message on connection {} before its definition", d.conn_id)))?;
                    visit(topic, tp, Some(Wire::Ros1), d.time, d.data)?;
                }
            }
        }
    }
    Ok(())
}
