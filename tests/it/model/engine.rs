//! The batching engine on real frames: own results, batching, overload, cancellation.
use crate::common::*;
use loopd::engine::{Engine, EngineConfig, EngineError};
use loopd::model::config::ModelConfig;
use loopd::model::device::DType;
use loopd::model::network::Variant;
use loopd::model::preprocess::ImageLimits;
use loopd::model::Model;
use std::time::{Duration, Instant};

fn corridor_frames(n: usize) -> Vec<bytes::Bytes> {
    (0..n).map(|i| std::fs::read(data(&format!("corridor/query/{i:07}.jpg"))).unwrap().into()).collect()
}

fn cos(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Each frame's descriptor, one request at a time (every forward pass has batch size 1).
async fn one_at_a_time(engine: &Engine, frames: &[bytes::Bytes]) -> Vec<Vec<f32>> {
    let mut alone = Vec::new();
    for f in frames {
        alone.push(engine.embed_image(f.clone(), Variant::FULL).await.unwrap());
    }
    alone
}

/// Every frame sent at once, one caller each.
fn all_at_once(
    engine: &Engine,
    frames: &[bytes::Bytes],
) -> Vec<tokio::task::JoinHandle<Result<Vec<f32>, EngineError>>> {
    frames
        .iter()
        .cloned()
        .map(|f| {
            let e = engine.clone();
            tokio::spawn(async move { e.embed_image(f, Variant::FULL).await })
        })
        .collect()
}

/// A small random-weight model: the flood and cancel tests are about queueing, not accuracy.
fn small_engine(cfg: EngineConfig) -> Engine {
    let mut mc = ModelConfig::default();
    mc.preprocess.width = 64;
    mc.preprocess.height = 64;
    let model = Model::new(mc, tch::Device::Cpu, DType::F32).unwrap();
    Engine::start(model, cfg, ImageLimits::default()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn sixty_four_concurrent_callers_each_get_their_own_descriptor() {
    let model = imagenet_model();
    model.randomize(3, true); // non-identity heads: the whole network is exercised
    let cfg = EngineConfig { max_batch: 16, max_delay: Duration::from_millis(20), ..Default::default() };
    let engine = Engine::start(model, cfg, ImageLimits::default()).unwrap();
    let frames = corridor_frames(64);
    // Each frame alone: one request at a time, so every forward pass has batch size 1.
    let alone = one_at_a_time(&engine, &frames).await;
    assert_eq!(engine.metrics().batch_size.max_bucket(), 1.0);
    let tasks = all_at_once(&engine, &frames);
    // A wrong descriptor for one frame (CI's run of 453a5b9 here, docs/ci.md) is named as such.
    for (k, d) in alone.iter().enumerate() {
        assert!(d.iter().all(|x| x.is_finite()), "frame {k} embedded alone has a non-finite descriptor");
    }
    for (i, t) in tasks.into_iter().enumerate() {
        let d = t.await.unwrap().unwrap();
        assert!(d.iter().all(|x| x.is_finite()), "caller {i} got a non-finite descriptor");
        let own = cos(&d, &alone[i]);
        assert!(own >= 0.9999, "caller {i}: cosine to its own frame alone is {own}");
        let best = (0..alone.len()).max_by(|&a, &b| cos(&d, &alone[a]).total_cmp(&cos(&d, &alone[b]))).unwrap();
        assert_eq!(
            best,
            i,
            "caller {i} got a descriptor closest to frame {best} (cosines {own} to its own, {} to frame {best}, {} \
             between the two alone)",
            cos(&d, &alone[best]),
            cos(&alone[i], &alone[best])
        );
    }
    assert!(engine.metrics().batch_size.max_bucket() > 1.0, "no batch larger than 1 was formed");
    assert_eq!(engine.metrics().images.load(std::sync::atomic::Ordering::Relaxed), 128);
}

/// Batch buckets (on by default on a GPU): batches padded with zero inputs up to a power of two
/// give each caller the descriptor of its own frame alone, and only bucket sizes run.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn padded_batches_give_each_caller_its_own_descriptor() {
    use std::sync::atomic::Ordering::Relaxed;
    assert_eq!(loopd::engine::buckets(12), vec![1, 2, 4, 8, 12]);
    assert_eq!(loopd::engine::buckets(1), vec![1]);
    let model = imagenet_model();
    model.randomize(3, true);
    let cfg = EngineConfig {
        max_batch: 8,
        max_delay: Duration::from_millis(1000),
        batch_buckets: Some(true),
        warm_up: false,
        ..Default::default()
    };
    let engine = Engine::start(model, cfg, ImageLimits::default()).unwrap();
    let frames = corridor_frames(5);
    let alone = one_at_a_time(&engine, &frames).await;
    assert_eq!(engine.metrics().padded.load(Relaxed), 0, "batches of 1 are a bucket: nothing to pad");
    // Five callers at once, within one batching window: one batch of 5, run as 8.
    let tasks = all_at_once(&engine, &frames);
    for (i, t) in tasks.into_iter().enumerate() {
        let d = t.await.unwrap().unwrap();
        let own = cos(&d, &alone[i]);
        assert!(own >= 0.9999, "caller {i}: cosine to its own frame alone is {own}");
    }
    let m = engine.metrics();
    assert_eq!(m.images.load(Relaxed), 10, "padding rows are not counted as images");
    let batched = m.batch_size.count() - 5;
    let padded = m.padded.load(Relaxed);
    assert!(batched >= 1 && padded > 0, "no padded batch ({batched} batches after the singles, {padded} padded)");
    // Whatever the split of the five callers into batches, each ran at a bucket size.
    assert!(padded <= 3 * batched, "{padded} padding rows over {batched} batches");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_flooded_queue_refuses_at_once_then_recovers() {
    let engine = small_engine(EngineConfig {
        max_batch: 2,
        max_delay: Duration::from_millis(1),
        queue_capacity: 4,
        warm_up: false,
        ..Default::default()
    });
    let frames = corridor_frames(40);
    let tasks: Vec<_> = frames
        .into_iter()
        .map(|f| {
            let e = engine.clone();
            tokio::spawn(async move {
                let t = Instant::now();
                (e.embed_image(f, Variant::FULL).await, t.elapsed())
            })
        })
        .collect();
    let (mut ok, mut refused) = (0, 0);
    for t in tasks {
        match t.await.unwrap() {
            (Ok(d), _) => {
                assert_eq!(d.len(), 2048);
                ok += 1
            }
            (Err(EngineError::Overloaded(4)), waited) => {
                assert!(waited < Duration::from_millis(50), "refusal took {waited:?}: it must be immediate");
                refused += 1
            }
            (Err(e), _) => panic!("unexpected error {e}"),
        }
    }
    assert!(refused > 0, "40 requests into a queue of 4 were all accepted");
    assert!(ok >= 4, "only {ok} served");
    let m = engine.metrics();
    assert_eq!(m.rejected_overload.load(std::sync::atomic::Ordering::Relaxed), refused);
    assert_eq!(m.queued.load(std::sync::atomic::Ordering::Relaxed), 0, "admissions leaked");
    // Recovered: a later request is served normally.
    let f = corridor_frames(1).pop().unwrap();
    assert_eq!(engine.embed_image(f, Variant::FULL).await.unwrap().len(), 2048);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_cancelled_request_costs_no_forward_pass() {
    use std::sync::atomic::Ordering::Relaxed;
    // A long batching window holds both requests in the queue while one is given up.
    let engine = small_engine(EngineConfig {
        max_batch: 8,
        max_delay: Duration::from_millis(600),
        warm_up: false,
        ..Default::default()
    });
    let mut frames = corridor_frames(3);
    let kept = {
        let e = engine.clone();
        let f = frames.remove(0);
        tokio::spawn(async move { e.embed_image(f, Variant::FULL).await })
    };
    // Dropped by its caller (timeout) while waiting in the batch window.
    let given_up =
        tokio::time::timeout(Duration::from_millis(100), engine.embed_image(frames.remove(0), Variant::FULL)).await;
    assert!(given_up.is_err(), "the request should still have been waiting");
    assert_eq!(kept.await.unwrap().unwrap().len(), 2048);
    let m = engine.metrics();
    assert_eq!(m.cancelled.load(Relaxed), 1);
    assert_eq!(m.images.load(Relaxed), 1, "only the kept request was computed");
    assert_eq!(m.batch_size.count(), 1);
    assert_eq!(m.queued.load(Relaxed), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_images_are_refused_by_the_engine_and_it_keeps_serving() {
    let engine = small_engine(EngineConfig { warm_up: false, ..Default::default() });
    let err = engine.embed_image(bytes::Bytes::from_static(b"not an image"), Variant::FULL).await;
    assert!(matches!(err, Err(EngineError::Image(_))), "{err:?}");
    let f = corridor_frames(1).pop().unwrap();
    assert!(engine.embed_image(f, Variant::FULL).await.is_ok());
    let mut registry = prometheus_client::registry::Registry::default();
    registry.register_collector(Box::new(engine.metrics().clone()));
    let mut text = String::new();
    prometheus_client::encoding::text::encode(&mut text, &registry).unwrap();
    assert!(text.contains("loopd_engine_images_total 1"), "{text}");
    assert!(text.contains("loopd_engine_batch_size_bucket{le=\"1.0\"} 1"), "{text}");
}

/// Requests of `n` callers at once in `lane`, each pushing `tag` into `done` when answered.
fn flood(
    engine: &Engine,
    lane: loopd::engine::Lane,
    tag: &'static str,
    n: usize,
    done: &std::sync::Arc<parking_lot::Mutex<Vec<&'static str>>>,
) -> Vec<tokio::task::JoinHandle<()>> {
    (0..n)
        .map(|_| {
            let (e, done, lane) = (engine.clone(), done.clone(), lane.clone());
            let x = tch::Tensor::randn([3, 64, 64], tch::kind::FLOAT_CPU);
            tokio::spawn(loopd::engine::in_lane(lane, async move {
                e.embed_input(x, Variant::FULL).await.unwrap();
                done.lock().push(tag);
            }))
        })
        .collect()
}

/// Waits until the engine holds at least `n` requests.
async fn queued_at_least(engine: &Engine, n: u64) {
    let start = Instant::now();
    while engine.metrics().queued.load(std::sync::atomic::Ordering::Relaxed) < n {
        assert!(start.elapsed() < Duration::from_secs(10), "fewer than {n} requests reached the engine in 10 s");
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
}

fn lane(name: &str, weight: u32) -> loopd::engine::Lane {
    loopd::engine::Lane { name: name.into(), weight }
}

/// Batches of 4; `shared_batch_ms` (0: whole batches while lanes share, as in the tests of the
/// shares themselves).
fn fair_engine_cut(shared_batch_ms: u64) -> Engine {
    small_engine(EngineConfig {
        max_batch: 4,
        max_delay: Duration::from_millis(1),
        queue_capacity: 512,
        warm_up: false,
        batch_buckets: Some(false),
        shared_batch_time: Duration::from_millis(shared_batch_ms),
        ..Default::default()
    })
}

fn fair_engine() -> Engine {
    fair_engine_cut(0)
}

/// A lane (tenant) that fills the queue delays another lane's request by about one batch, not
/// by its whole backlog: each batch is filled from the lanes with work by round robin.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_lane_that_floods_the_engine_delays_another_by_about_one_batch() {
    let engine = fair_engine();
    let done = std::sync::Arc::new(parking_lot::Mutex::new(Vec::new()));
    let mut tasks = flood(&engine, lane("bulk", 1), "bulk", 60, &done);
    queued_at_least(&engine, 50).await;
    tasks.extend(flood(&engine, lane("other", 1), "other", 1, &done));
    for t in tasks {
        t.await.unwrap();
    }
    let order = done.lock().clone();
    let before = order.iter().position(|t| *t == "other").unwrap();
    // At most the batch running when it arrived and its own batch's other three.
    assert!(before <= 8, "60 queued requests of another lane: {before} were answered before this one: {order:?}");
}

/// Lanes with work share each batch in proportion to their weights (3:1 here); a lane alone
/// fills whole batches. With batches cut to one image while lanes share (`shared_batch_ms`),
/// the weights hold across batches (a lane's turn goes on in the next batch).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn lanes_share_the_batches_by_weight_and_a_lane_alone_fills_them() {
    for shared_batch_ms in [0, 1] {
        let engine = fair_engine_cut(shared_batch_ms);
        let done = std::sync::Arc::new(parking_lot::Mutex::new(Vec::new()));
        let mut tasks = Vec::new();
        for _ in 0..40 {
            tasks.extend(flood(&engine, lane("heavy", 3), "heavy", 1, &done));
            tasks.extend(flood(&engine, lane("light", 1), "light", 1, &done));
        }
        for t in tasks {
            t.await.unwrap();
        }
        let order = done.lock().clone();
        // Past the first two batches (formed while the requests were still arriving), while
        // both lanes have work: 32 places.
        let heavy = order[8..40].iter().filter(|t| **t == "heavy").count();
        assert!(
            (20..=28).contains(&heavy),
            "shared batch {shared_batch_ms} ms: heavy (weight 3) got {heavy} of 32 places, light the rest: {order:?}"
        );
        let m = engine.metrics();
        assert_eq!(m.images.load(std::sync::atomic::Ordering::Relaxed), 80);
        if shared_batch_ms == 0 {
            // Once heavy has none left, light runs alone, in full batches.
            assert!(m.batch_size.sum() / m.batch_size.count() as f64 >= 3.0, "batches were not kept full");
        }
    }
}

/// While two lanes have work, batches are cut to what runs in the shared batch time (here so
/// short that one image is a batch): a closed-loop caller of one lane waits for at most about
/// one short batch of the flooding lane's, not for a whole batch of 8. Once it has been gone for
/// the share window, the flooding lane runs whole batches again.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn while_lanes_share_the_model_batches_are_cut_to_the_shared_time() {
    use std::sync::atomic::Ordering::Relaxed;
    let engine = small_engine(EngineConfig {
        max_batch: 8,
        max_delay: Duration::from_millis(1),
        queue_capacity: 512,
        warm_up: false,
        batch_buckets: Some(false),
        shared_batch_time: Duration::from_nanos(1),
        // Long enough that a test thread starved by a busy machine between two of its requests
        // is still a lane with work (CI: 300 ms once let a whole batch of bulk's in, [10, 2, 2, 3, 10]).
        share_window: Duration::from_secs(2),
        ..Default::default()
    });
    let done = std::sync::Arc::new(parking_lot::Mutex::new(Vec::new()));
    let mut tasks = flood(&engine, lane("bulk", 1), "bulk", 200, &done);
    queued_at_least(&engine, 150).await;
    // The other lane: one request at a time; how many images the engine ran while each waited
    // (its own included).
    let images = || engine.metrics().images.load(Relaxed);
    let mut waited = Vec::new();
    for _ in 0..5 {
        let before = images();
        for t in flood(&engine, lane("other", 1), "other", 1, &done) {
            t.await.unwrap();
        }
        waited.push(images() - before);
    }
    // The first may meet a whole batch formed while bulk was alone; the others short ones only.
    assert!(waited[1..].iter().all(|&n| n <= 4), "images run while each of other's requests waited: {waited:?}");
    assert!(engine.metrics().shared_batches.load(Relaxed) > 0);
    for t in tasks.drain(..) {
        t.await.unwrap();
    }
    // Alone again past the window: whole batches.
    tokio::time::sleep(Duration::from_millis(2200)).await;
    let m = engine.metrics();
    let (count0, sum0) = (m.batch_size.count(), m.batch_size.sum());
    let shared0 = m.shared_batches.load(Relaxed);
    for t in flood(&engine, lane("bulk", 1), "bulk", 64, &done) {
        t.await.unwrap();
    }
    let mean = (m.batch_size.sum() - sum0) / (m.batch_size.count() - count0) as f64;
    assert!(mean >= 4.0, "a lane alone ran batches of {mean:.1} on average");
    assert_eq!(m.shared_batches.load(Relaxed), shared0, "batches were cut with one lane alone");
}
