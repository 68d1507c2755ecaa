//! AddFrame / AddAndQuery / StreamFrames request messages as protobuf bytes: decoded,
//! converted and validated (robot id, timestamp, frame id, pose, metadata, query options).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loopd::api::grpc::parse_add_frame;

fuzz_target!(|data: &[u8]| {
    let _ = parse_add_frame(data);
});
