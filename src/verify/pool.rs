//! Feature extraction and candidate checks on a bounded set of blocking threads, never on the
//! request executor nor on the model thread.
use super::depth::DepthImage;
use super::error::VerifyError;
use super::features::{from_image_bytes, FeatureParams, Features, STEREO_BYTES};
use super::{Checks, LoopMatch};
use crate::index::query::Match;
use crate::model::preprocess::ImageLimits;
use std::sync::Arc;
use tokio::sync::Semaphore;

#[derive(Clone, Debug)]
pub struct VerifyConfig {
    pub features: FeatureParams,
    /// Largest stored feature record per frame; the weakest features beyond it are dropped.
    pub max_feature_bytes: usize,
    /// Extractions and checks running at once.
    pub workers: usize,
}

impl Default for VerifyConfig {
    fn default() -> Self {
        Self {
            features: FeatureParams::default(),
            max_feature_bytes: 64 << 10,
            workers: std::thread::available_parallelism().map_or(1, |n| n.get()),
        }
    }
}

#[derive(Clone)]
pub struct Verifier {
    cfg: Arc<VerifyConfig>,
    slots: Arc<Semaphore>,
    /// Images whose features were extracted (`loopd_features_extracted` in /metrics).
    extracted: Arc<std::sync::atomic::AtomicU64>,
}

impl Verifier {
    pub fn new(cfg: VerifyConfig) -> Self {
        let slots = Arc::new(Semaphore::new(cfg.workers.max(1)));
        Self { cfg: Arc::new(cfg), slots, extracted: Default::default() }
    }

    pub fn config(&self) -> &VerifyConfig {
        &self.cfg
    }

    /// The count of images whose features were extracted.
    pub fn extracted(&self) -> Arc<std::sync::atomic::AtomicU64> {
        self.extracted.clone()
    }

    /// Runs `f` on a blocking thread once a worker slot is free.
    async fn run<T: Send + 'static>(&self, f: impl FnOnce() -> T + Send + 'static) -> Result<T, VerifyError> {
        let permit =
            self.slots.clone().acquire_owned().await.map_err(|_| VerifyError::Failed("verifier stopped".into()))?;
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            f()
        })
        .await
        .map_err(|e| VerifyError::Failed(format!("verification worker failed: {e}")))
    }

    /// ORB features of an encoded image, capped to the stored size limit (counting each
    /// keypoint's depth when the frame has depth).
    pub async fn extract(
        &self,
        image: bytes::Bytes,
        limits: ImageLimits,
        depth: bool,
    ) -> Result<Features, VerifyError> {
        let cfg = self.cfg.clone();
        self.extracted.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut f = self.run(move || from_image_bytes(&image, &limits, &cfg.features)).await??;
        let bytes = f.descriptor_bytes;
        // A stereo frame's record ends with its rig's focal length times baseline.
        let fixed = Features::encoded_len_of(0, bytes, depth) + if depth { STEREO_BYTES } else { 0 };
        let fit = self.cfg.max_feature_bytes.saturating_sub(fixed)
            / (Features::encoded_len_of(1, bytes, depth) - Features::encoded_len_of(0, bytes, depth)).max(1);
        f.truncate(fit);
        Ok(f)
    }

    /// A frame's depth image, decoded on a worker ([`DepthImage::decode`]).
    pub async fn decode_depth(
        &self,
        depth: bytes::Bytes,
        scale: f64,
        limits: ImageLimits,
    ) -> Result<DepthImage, VerifyError> {
        self.run(move || DepthImage::decode(&depth, scale, &limits)).await?
    }

    /// [`super::check`] on a worker.
    pub async fn check(
        &self,
        query: Option<Result<Arc<Features>, String>>,
        candidates: Vec<(Match, Option<Features>)>,
        checks: Checks,
    ) -> Result<Vec<LoopMatch>, VerifyError> {
        self.run(move || {
            let query = query.as_ref().map(|q| q.as_deref().map_err(String::as_str));
            super::check(query, candidates, &checks)
        })
        .await
    }
}
