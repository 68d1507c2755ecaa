//! rosbag2 MCAP files through the `mcap` crate's sans-io reader (chunks compressed with zstd or
//! lz4, chunk CRCs checked). Its `MessageStream` sets no record length limit, and a record that
//! claims 2^64 bytes then overflows an index and panics (found by the `sequence_upload` fuzz
//! target); the reader here bounds every record and decompressed chunk by the file's own size, and
//! parses only the records it needs (the crate's attachment parser slices past a short record's
//! end: found the same way).
use super::msgs::Wire;
use super::{BagError, Visit};
use mcap::records::{op, Record};
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::collections::HashMap;

pub const MAGIC: &[u8] = b"\x89MCAP0\r\n";

fn err(e: mcap::McapError) -> BagError {
    let why = match e {
        mcap::McapError::UnexpectedEof => "the file ends in the middle of a record (truncated?)".to_string(),
        mcap::McapError::Io(e) => format!("a compressed chunk does not decompress (damaged?): {e}"),
        other => other.to_string(),
    };
    BagError::Corrupt(format!("MCAP: {why}"))
}

/// A channel as its record declares it: topic, schema (type) name, message encoding.
struct Channel {
    topic: String,
    msg_type: String,
    wire: Option<Wire>,
}

/// Every message in file order.
pub fn visit(bytes: &[u8], visit: &mut Visit) -> Result<(), BagError> {
    let options = LinearReaderOptions::default().with_record_length_limit(bytes.len()).with_validate_chunk_crcs(true);
    let mut reader = LinearReader::new_with_options(options);
    let mut rest = bytes;
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, Channel> = HashMap::new();
    while let Some(event) = reader.next_event() {
        let (opcode, data) = match event.map_err(err)? {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(rest.len());
                reader.insert(n).copy_from_slice(&rest[..n]);
                reader.notify_read(n);
                rest = &rest[n..];
                continue;
            }
            LinearReadEvent::Record { opcode, data } => (opcode, data),
        };
        if ![op::SCHEMA, op::CHANNEL, op::MESSAGE].contains(&opcode) {
            continue;
        }
        match mcap::parse_record(opcode, data).map_err(err)? {
            Record::Schema { header, .. } => {
                schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let msg_type = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                // rosbag2 writes CDR; a topic in another encoding is listed but never decoded.
                let wire = (c.message_encoding == "cdr").then_some(Wire::Cdr);
                channels.insert(c.id, Channel { topic: c.topic, msg_type, wire });
            }
            Record::Message { header, data } => {
                let c = channels.get(&header.channel_id).ok_or_else(|| {
                    BagError::Corrupt(format!("MCAP: a message on channel {} before its definition", header.channel_id))
                })?;
                visit(&c.topic, &c.msg_type, c.wire, header.log_time, &data)?;
            }
            _ => {}
        }
    }
    Ok(())
}
