//! Overload and slow clients (issue #14), against the real `loopd serve` process: a burst of 64
//! clients at a small queue is refused at once with RESOURCE_EXHAUSTED / 429 (never a timeout
//! cascade) while the server's RSS stays bounded, and it serves normally after; connections
//! that stall (half-sent headers, no HTTP/2 preface, an idle keep-alive, a stalled or trickled
//! body) are closed by their deadlines, more connections than the limit are refused, and an idle
//! gRPC channel stays usable.
use crate::common::proc::Loopd;
use crate::common::*;
use loopd::pb;
use loopd::pb::loopd_client::LoopdClient;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

fn rss_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: f64 =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:")).unwrap().trim().trim_end_matches(" kB").parse().unwrap();
    kb / 1024.0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_64_clients_is_refused_fast_with_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let (server, _) = Loopd::start(dir.path(), &["--queue-capacity", "4", "--max-batch", "4"]).await;
    let mut c = LoopdClient::connect(server.grpc_url()).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "o".into(), ..Default::default() }).await.unwrap();
    c.add_and_query(corridor_frame("o", "warm", 0)).await.unwrap();
    let before = rss_mib(server.pid());

    // 64 robots, 6 frames each, all at once, each on its own connection.
    let sampling = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let pid = server.pid();
    let sampler = {
        let sampling = sampling.clone();
        tokio::spawn(async move {
            let mut peak: f64 = 0.0;
            while sampling.load(std::sync::atomic::Ordering::Relaxed) {
                peak = peak.max(rss_mib(pid));
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            peak
        })
    };
    let t = Instant::now();
    let robots: Vec<_> = (0..64)
        .map(|r| {
            let url = server.grpc_url();
            tokio::spawn(async move {
                let mut c = LoopdClient::connect(url).await.unwrap();
                let mut outcomes = Vec::new();
                for i in 0..6 {
                    let sent = Instant::now();
                    let r = c.add_and_query(corridor_frame("o", &format!("r{r}"), r * 6 + i)).await;
                    outcomes.push((r.map(|_| ()).map_err(|s| s.code()), sent.elapsed()));
                }
                outcomes
            })
        })
        .collect();
    let mut outcomes = Vec::new();
    for r in robots {
        outcomes.extend(r.await.unwrap());
    }
    let burst = t.elapsed();
    sampling.store(false, std::sync::atomic::Ordering::Relaxed);
    let peak = sampler.await.unwrap();
    let ok = outcomes.iter().filter(|(r, _)| r.is_ok()).count();
    let mut refused: Vec<Duration> =
        outcomes.iter().filter(|(r, _)| *r == Err(tonic::Code::ResourceExhausted)).map(|(_, t)| *t).collect();
    let other: Vec<_> = outcomes.iter().filter(|(r, _)| r.is_err() && !refused.is_empty()).collect();
    refused.sort();
    let p99 = refused.get(refused.len() * 99 / 100).copied().unwrap_or_default();
    eprintln!(
        "burst of 384 frames from 64 robots in {burst:.2?}: {ok} stored, {} refused (RESOURCE_EXHAUSTED, p50 {:.2?}, \
         p99 {p99:.2?}); RSS {before:.0} MiB before, peak {peak:.0} MiB",
        refused.len(),
        refused.get(refused.len() / 2).copied().unwrap_or_default()
    );
    assert!(other.iter().all(|(r, _)| *r == Err(tonic::Code::ResourceExhausted)), "only refusals: {other:?}");
    assert!(refused.len() > 100 && ok > 0, "a queue of 4 against 64 robots refuses most of the burst");
    assert!(p99 < Duration::from_millis(500), "refusals must be quick, p99 {p99:?}");
    assert!(peak - before < 1024.0, "RSS grew by {:.0} MiB in the burst (bound 1 GiB)", peak - before);
    // A refused frame is neither decoded for its features nor searched: only the admitted ones
    // (and the warm-up frame) were.
    let extracted = features_extracted(&server).await;
    assert_eq!(extracted, ok as u64 + 1, "features extracted for {extracted} images, {ok} admitted in the burst");

    // After the burst: normal service, and the memory back under the bound.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let t = Instant::now();
    c.add_and_query(corridor_frame("o", "after", 1)).await.unwrap();
    let after = rss_mib(server.pid());
    eprintln!("after the burst: a frame in {:.2?}, RSS {after:.0} MiB", t.elapsed());
    assert!(after - before < 1024.0);
    let s = c.get_session(pb::GetSessionRequest { id: "o".into() }).await.unwrap().into_inner();
    assert_eq!(s.frames as usize, ok + 2, "every acknowledged frame stored, nothing else");
    server.stop().await;
}

/// Reads until the server closes the connection (or errors); how long that took.
async fn closed_within(s: &mut TcpStream, limit: Duration) -> Duration {
    let t = Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(limit.saturating_sub(t.elapsed()), s.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => return t.elapsed(),
            Ok(Ok(_)) => {}
            Err(_) => panic!("connection still open after {limit:?}"),
        }
    }
}

/// `loopd_features_extracted` in `/metrics`: images whose local features were extracted.
async fn features_extracted(server: &Loopd) -> u64 {
    let metrics = reqwest::get(format!("{}/metrics", server.http_url())).await.unwrap().text().await.unwrap();
    let line = metrics.lines().find_map(|l| l.strip_prefix("loopd_features_extracted_total "));
    line.expect("loopd_features_extracted_total in /metrics").parse().unwrap()
}

/// The server's open HTTP connections (`/metrics`), this request's own included; None when the
/// request is refused (the limit still full of connections the server has not seen close yet).
async fn open_http_connections(server: &Loopd) -> Option<usize> {
    let metrics = reqwest::get(format!("{}/metrics", server.http_url())).await.ok()?.text().await.ok()?;
    let line = metrics.lines().find_map(|l| l.strip_prefix("loopd_open_connections{listener=\"http\"} "));
    Some(line.expect("loopd_open_connections in /metrics").parse().unwrap())
}

/// Waits until the server holds no HTTP connection but the one asking; the clients closed theirs,
/// so that must happen within the idle deadline (2 s here).
async fn http_connections_settle(server: &Loopd) {
    let t = Instant::now();
    loop {
        let open = open_http_connections(server).await;
        if open.is_some_and(|n| n <= 1) {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(3), "HTTP connections still open on the server after 3 s: {open:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_connections_are_closed_and_the_limit_holds() {
    let dir = tempfile::tempdir().unwrap();
    let flags = [
        "--header-timeout-secs",
        "1",
        "--idle-timeout-secs",
        "2",
        "--request-timeout-secs",
        "3",
        "--max-connections",
        "8",
    ];
    let (server, _) = Loopd::start(dir.path(), &flags).await;
    let limit = Duration::from_secs(6);

    // Half-sent headers.
    let mut s = TcpStream::connect(server.http).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n").await.unwrap();
    eprintln!("half-sent headers: closed after {:.2?}", closed_within(&mut s, limit).await);
    // No HTTP/2 preface, and half a preface.
    s = TcpStream::connect(server.grpc).await.unwrap();
    eprintln!("gRPC without a preface: closed after {:.2?}", closed_within(&mut s, limit).await);
    s = TcpStream::connect(server.grpc).await.unwrap();
    s.write_all(b"PRI * HTTP/2.0\r\n").await.unwrap();
    eprintln!("half a preface: closed after {:.2?}", closed_within(&mut s, limit).await);
    // An idle keep-alive after one answered request.
    s = TcpStream::connect(server.http).await.unwrap();
    s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    eprintln!("idle keep-alive: closed after {:.2?}", closed_within(&mut s, limit).await);
    // A stalled body.
    s = TcpStream::connect(server.http).await.unwrap();
    s.write_all(b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{\"id\"")
        .await
        .unwrap();
    eprintln!("stalled body: closed after {:.2?}", closed_within(&mut s, limit).await);
    // A body trickled a byte every 0.5 s (never idle): 408 at the request deadline.
    s = TcpStream::connect(server.http).await.unwrap();
    s.write_all(
        b"POST /v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n",
    )
    .await
    .unwrap();
    let t = Instant::now();
    let mut answer = Vec::new();
    while t.elapsed() < limit {
        if s.write_all(b" ").await.is_err() {
            break;
        }
        let mut buf = [0u8; 1024];
        match tokio::time::timeout(Duration::from_millis(500), s.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => break,
            Ok(Ok(n)) => answer.extend_from_slice(&buf[..n]),
            Err(_) => {}
        }
    }
    let answer = String::from_utf8_lossy(&answer).to_string();
    eprintln!("trickled body: {:?} after {:.2?}", answer.lines().next(), t.elapsed());
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(t.elapsed() < limit);

    // The limit: 8 open connections, the 9th closed at once; a slot frees when one closes.
    // First every connection above gone on the server's side too (CI's run of a03d996, on a
    // loaded machine: one of the 8 refused with a reset right after the trickled body's 408).
    drop(s);
    http_connections_settle(&server).await;
    // The connection that asked for /metrics last is closed on the client's side, but the server
    // may not have read that close yet (CI's run of 2c3707f, the fuzz build beside it: one of the
    // 8 closed unanswered). So a connection closed unanswered is tried again:
    // what is asserted is that 8 are then held and answered at once, and the 9th is not (within 1 s,
    // under the idle deadline of 2 s that would free the slots the held ones take).
    let mut held = Vec::new();
    let t = Instant::now();
    while held.len() < 8 {
        let mut s = TcpStream::connect(server.http).await.unwrap();
        let _ = s.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await;
        let mut buf = [0u8; 256];
        if matches!(s.read(&mut buf).await, Ok(n) if n > 0) {
            held.push(s);
            continue;
        }
        assert!(t.elapsed() < Duration::from_secs(1), "only {} connections answered under a limit of 8", held.len());
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    eprintln!("8 connections held under a limit of 8 after {:.2?}", t.elapsed());
    let mut ninth = TcpStream::connect(server.http).await.unwrap();
    let _ = ninth.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n").await;
    let took = closed_within(&mut ninth, Duration::from_millis(500)).await;
    eprintln!("9th connection over a limit of 8: closed after {took:.2?}");
    held.clear();
    http_connections_settle(&server).await;
    assert_eq!(reqwest::get(format!("{}/healthz", server.http_url())).await.unwrap().status(), 200);

    // A stream whose answers are never read: the server holds at most 16 answers of it, the
    // client's HTTP/2 window takes some more (2 MiB by default), then the server stops taking
    // its frames and flow control stops the robot. Answers of 300 matches (a map of 300 frames)
    // fill that window quickly. Everyone else is served as usual.
    let mut c = LoopdClient::connect(server.grpc_url()).await.unwrap();
    c.create_session(pb::CreateSessionRequest { id: "slow".into(), ..Default::default() }).await.unwrap();
    let dim = server.dim().await;
    let descriptor_frame = |i: usize| pb::AddFrameRequest {
        session_id: "slow".into(),
        robot_id: "slow".into(),
        timestamp: Some(i as f64),
        content: Some(pb::add_frame_request::Content::Descriptor(pb::Descriptor {
            values: (0..dim).map(|k| ((k * 31 + i * 7) % 97) as f32 - 48.0).collect(),
            ..Default::default()
        })),
        options: Some(pb::QueryOptions { k: Some(300), verify: Some(false), ..Default::default() }),
        ..Default::default()
    };
    for i in 0..300 {
        c.add_frame(descriptor_frame(i)).await.unwrap();
    }
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let _unread = c.stream_frames(tokio_stream::wrappers::ReceiverStream::new(rx)).await.unwrap();
    let mut sent = 0;
    for i in 300..3000 {
        match tokio::time::timeout(Duration::from_millis(300), tx.send(descriptor_frame(i))).await {
            Ok(Ok(())) => sent += 1,
            _ => break,
        }
    }
    let mut other = LoopdClient::connect(server.grpc_url()).await.unwrap();
    let t = Instant::now();
    let stored = other.get_session(pb::GetSessionRequest { id: "slow".into() }).await.unwrap().into_inner().frames;
    eprintln!(
        "a stream never read: the robot could send {sent} frames ({} stored) before flow control stopped it; \
         another client answered in {:.2?}",
        stored - 300,
        t.elapsed()
    );
    assert!(sent < 2700, "the server kept taking frames whose answers nobody reads");
    assert!(stored - 300 <= sent as u64);

    // A gRPC channel idle for longer than the idle deadline stays usable.
    let mut c = LoopdClient::connect(server.grpc_url()).await.unwrap();
    c.list_sessions(pb::ListSessionsRequest {}).await.unwrap();
    tokio::time::sleep(Duration::from_secs(3)).await;
    c.list_sessions(pb::ListSessionsRequest {}).await.expect("an idle gRPC channel still works");
    server.stop().await;
}
