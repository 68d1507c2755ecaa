//! What both APIs do, written once: gRPC and HTTP only translate to and from these calls, and
//! reach the engine and the store through nothing else (sequence jobs call it, `jobs.rs`).
mod search;

use super::error::ApiError;
use super::kept::{loop_records, QueryFrame};
use crate::engine::Engine;
use crate::index::graph::IndexKind;
use crate::index::query::{LoopQuery, Pose, Scope};
use crate::index::Storage;
use crate::model::network::Variant;
use crate::model::preprocess::ImageLimits;
use crate::store::record::{Camera, FrameHeader};
use crate::store::{NewFrame, NewSession, Session, SessionInfo, Store, MAX_CLIENT_FRAME_ID};
use crate::verify::confidence::Calibrator;
use crate::verify::features::Features;
use crate::verify::geometric::VerifyParams;
use crate::verify::pool::{Verifier, VerifyConfig};
use crate::verify::sequence::{self, Place};
pub use crate::verify::LoopMatch;
use crate::verify::{self, Checks, SequenceInputs};
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

#[derive(Clone)]
pub struct LoopService {
    /// Every served model's engine, the default first (`serve --models`; never empty).
    pub models: Vec<Engine>,
    pub store: Arc<Store>,
    pub verifier: Verifier,
    /// Each served model's calibrated confidence, in `models`' order (None: its sessions'
    /// answers carry none).
    pub calibrators: Vec<Option<Arc<Calibrator>>>,
    /// Answers whose candidates could not be kept (storage failed after the frame was stored).
    pub loops_not_kept: Arc<std::sync::atomic::AtomicU64>,
}

/// Where a query's past comes from for sequence verification.
enum History {
    /// A live frame of this robot (not stored yet): the robot's newest stored frames, then it.
    Live(Option<String>),
    /// A stored frame: its own trajectory up to it.
    Stored(u64),
}

/// What a query brings to geometric verification: its features, or why it has none.
enum QueryFeatures {
    Some(Arc<Features>),
    None(String),
}

/// A frame's picture made ready: its descriptor, the local features of an image, and its
/// thumbnail when the session keeps them.
struct Prepared {
    descriptor: Vec<f32>,
    features: QueryFeatures,
    thumbnail: Option<Vec<u8>>,
}

/// A frame's picture: image bytes to embed, or a descriptor computed elsewhere.
pub enum Content {
    /// An encoded image, and the depth image registered to it if the frame has one (16-bit in
    /// the session camera's `depth_scale` units, or float metres), or the right image of a stereo
    /// pair (the session camera's `stereo`): loops verified with it get metric poses.
    Image { image: Bytes, depth: Option<Bytes>, right: Option<Bytes> },
    /// A descriptor the client computed, and the descriptor space it says it comes from.
    Descriptor(Vec<f32>, Option<String>),
    /// An image of this server's model embedded, and its features extracted, ahead (sequence
    /// jobs do both in batches): it is verified and kept like an image sent to `add_and_query`.
    Embedded { descriptor: Vec<f32>, features: Result<Features, String> },
}

/// Query options as sent: unset fields fall back to the session's defaults.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
#[schema(as = QueryOptions)]
pub struct QueryOverrides {
    #[schema(minimum = 1, maximum = 1000)]
    pub k: Option<usize>,
    pub min_score: Option<f32>,
    /// Candidates below this calibrated confidence are not returned.
    #[schema(minimum = 0, maximum = 1)]
    pub min_confidence: Option<f32>,
    pub exclude_last_frames: Option<usize>,
    pub exclude_last_seconds: Option<f64>,
    pub scope: Option<Scope>,
    #[schema(value_type = Option<Vec<f64>>, min_items = 2, max_items = 2)]
    pub time_range: Option<(f64, f64)>,
    #[schema(value_type = Option<Vec<u64>>, min_items = 2, max_items = 2)]
    pub frame_id_range: Option<(u64, u64)>,
    /// Geometric verification of the best candidates on or off.
    pub verify: Option<bool>,
    /// How many candidates are checked (K).
    #[schema(minimum = 1, maximum = 50)]
    pub verify_candidates: Option<usize>,
    /// Inliers needed for a verified loop.
    #[schema(minimum = 8, maximum = 10000)]
    pub min_inliers: Option<usize>,
    /// Sequence verification on or off.
    pub sequence: Option<bool>,
    /// Frames compared along the trajectories (L).
    #[schema(minimum = 1, maximum = 200)]
    pub sequence_length: Option<usize>,
    /// Margin for a sequence-verified loop.
    pub min_sequence_margin: Option<f32>,
}

impl QueryOverrides {
    /// These options where set, `base`'s elsewhere.
    pub fn over(&self, base: &QueryOverrides) -> QueryOverrides {
        QueryOverrides {
            k: self.k.or(base.k),
            min_score: self.min_score.or(base.min_score),
            min_confidence: self.min_confidence.or(base.min_confidence),
            exclude_last_frames: self.exclude_last_frames.or(base.exclude_last_frames),
            exclude_last_seconds: self.exclude_last_seconds.or(base.exclude_last_seconds),
            scope: self.scope.or(base.scope),
            time_range: self.time_range.or(base.time_range),
            frame_id_range: self.frame_id_range.or(base.frame_id_range),
            verify: self.verify.or(base.verify),
            verify_candidates: self.verify_candidates.or(base.verify_candidates),
            min_inliers: self.min_inliers.or(base.min_inliers),
            sequence: self.sequence.or(base.sequence),
            sequence_length: self.sequence_length.or(base.sequence_length),
            min_sequence_margin: self.min_sequence_margin.or(base.min_sequence_margin),
        }
    }

    pub fn apply(&self, base: &LoopQuery) -> LoopQuery {
        let mut q = base.clone();
        if let Some(v) = self.k {
            q.k = v;
        }
        if let Some(v) = self.min_score {
            q.min_score = v;
        }
        if let Some(v) = self.min_confidence {
            q.min_confidence = v;
        }
        if let Some(v) = self.exclude_last_frames {
            q.exclude_last_frames = v;
        }
        if let Some(v) = self.exclude_last_seconds {
            q.exclude_last_seconds = v;
        }
        if let Some(v) = self.scope {
            q.scope = v;
        }
        if self.time_range.is_some() {
            q.time_range = self.time_range;
        }
        if self.frame_id_range.is_some() {
            q.frame_id_range = self.frame_id_range;
        }
        if let Some(v) = self.verify {
            q.verify.geometric = v;
        }
        if let Some(v) = self.verify_candidates {
            q.verify.candidates = v;
        }
        if let Some(v) = self.min_inliers {
            q.verify.min_inliers = v;
        }
        if let Some(v) = self.sequence {
            q.verify.sequence = v;
        }
        if let Some(v) = self.sequence_length {
            q.verify.sequence_length = v;
        }
        if let Some(v) = self.min_sequence_margin {
            q.verify.min_sequence_margin = v;
        }
        q
    }
}

/// A keyframe as a client sends it, over either API.
pub struct FrameInput {
    pub robot_id: String,
    /// Required (the exclusion windows and time ranges depend on it); optional here so that the
    /// policy lives in one place, [`FrameInput::check`].
    pub timestamp: Option<f64>,
    pub frame_id: Option<u64>,
    pub pose: Option<Pose>,
    pub metadata: Option<serde_json::Value>,
    pub content: Content,
    /// A thumbnail made ahead (sequence jobs embed ahead, so their frames come as descriptors);
    /// None: made here from the image when the session keeps thumbnails.
    pub thumbnail: Option<Vec<u8>>,
    /// The client's idempotency key: a write sent again with it stores nothing and answers
    /// the first write's frame id (`store::keys`).
    pub idempotency_key: Option<String>,
}

impl FrameInput {
    /// Everything the request carries, checked before it takes a model slot.
    fn check(&self) -> Result<f64, ApiError> {
        check_robot_id(&self.robot_id)?;
        let t = self.timestamp.ok_or_else(|| ApiError::InvalidArgument("timestamp is required".into()))?;
        if !t.is_finite() {
            return Err(ApiError::InvalidArgument("timestamp must be a finite number".into()));
        }
        if self.frame_id.is_some_and(|id| id > MAX_CLIENT_FRAME_ID) {
            return Err(ApiError::InvalidArgument(format!("frame_id must be at most {MAX_CLIENT_FRAME_ID}")));
        }
        if let Some(key) = &self.idempotency_key {
            crate::store::keys::check_key(key)?;
        }
        if self.metadata.as_ref().is_some_and(|m| !m.is_object()) {
            return Err(ApiError::InvalidArgument("metadata must be a JSON object".into()));
        }
        if let Some(p) = &self.pose {
            let v = [p.x, p.y, p.z, p.qx, p.qy, p.qz, p.qw];
            if v.iter().any(|x| !x.is_finite()) {
                return Err(ApiError::InvalidArgument("pose values must be finite numbers".into()));
            }
        }
        Ok(t)
    }

    /// Everything a request carries checked, as the service does before a frame takes a model
    /// slot (the fuzz targets' entry).
    pub fn validate(&self, opts: &QueryOverrides) -> Result<(), ApiError> {
        self.check()?;
        opts.apply(&LoopQuery::default()).validate().map_err(ApiError::from)
    }

    /// The stored frame, once its descriptor (and the image's features) are known.
    fn into_new_frame(self, timestamp: f64, prepared: Prepared) -> NewFrame {
        NewFrame {
            frame_id: self.frame_id,
            robot_id: self.robot_id,
            timestamp,
            pose: self.pose,
            metadata: self.metadata,
            descriptor: prepared.descriptor,
            features: match prepared.features {
                QueryFeatures::Some(f) => Some(f.encode()),
                QueryFeatures::None(_) => None,
            },
            thumbnail: self.thumbnail.or(prepared.thumbnail),
            idempotency_key: self.idempotency_key,
        }
    }
}

/// A frame's thumbnail when `wanted`, off the async workers; one that cannot be made is left
/// out (the frame itself is still stored, or refused by the model for the same picture).
pub async fn make_thumbnail(bytes: &Bytes, limits: ImageLimits, wanted: bool) -> Option<Vec<u8>> {
    if !wanted {
        return None;
    }
    let bytes = bytes.clone();
    match tokio::task::spawn_blocking(move || crate::inspect::thumbnail::make(&bytes, &limits)).await {
        Ok(Ok(t)) => Some(t),
        Ok(Err(e)) => {
            tracing::debug!(error = %e, "no thumbnail");
            None
        }
        Err(e) => {
            tracing::warn!(error = %e, "thumbnail worker failed");
            None
        }
    }
}

pub(super) fn check_robot_id(robot: &str) -> Result<(), ApiError> {
    match crate::store::robot_id_error(robot) {
        Some(e) => Err(ApiError::InvalidArgument(e.into())),
        None => Ok(()),
    }
}

pub enum QueryTarget {
    Content(Content),
    Frame(u64),
}

/// A new session: unset fields take their defaults (the server picks the id).
#[derive(Clone, Debug, Default, Deserialize, Serialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
pub struct CreateSession {
    pub id: Option<String>,
    pub name: String,
    pub storage: Storage,
    pub default_query: QueryOverrides,
    /// The camera of the session's frames: verified loops then carry the relative pose.
    pub camera: Option<Camera>,
    /// Keep a small JPEG of each frame (the loop inspector shows them).
    pub thumbnails: bool,
    /// How its frames are searched (default auto: exact until the session is large).
    pub index: IndexKind,
    /// The served model whose descriptors it holds (None: the server's default).
    pub model: Option<String>,
}

impl LoopService {
    pub fn new(engine: Engine, store: Arc<Store>, verify: VerifyConfig, calibrator: Option<Calibrator>) -> Self {
        Self::with_models(vec![(engine, calibrator)], store, verify)
    }

    /// A service of several models' engines, each with its calibrator, the default first (at
    /// least one).
    pub fn with_models(models: Vec<(Engine, Option<Calibrator>)>, store: Arc<Store>, verify: VerifyConfig) -> Self {
        assert!(!models.is_empty(), "a service serves at least one model");
        let (models, calibrators) = models.into_iter().map(|(e, c)| (e, c.map(Arc::new))).unzip();
        let service =
            Self { models, store, verifier: Verifier::new(verify), calibrators, loops_not_kept: Default::default() };
        service.report_foreign_sessions();
        service
    }

    /// Says at start which stored sessions none of this server's models can add to or query by
    /// image.
    fn report_foreign_sessions(&self) {
        for s in self.store.list() {
            if self.model_of(&s.meta.descriptor_id).is_none() {
                tracing::warn!(
                    session = %s.meta.id,
                    session_descriptor_id = %s.meta.descriptor_id,
                    served = %self.served_ids(),
                    "session was built by a model this server does not serve: its frames are kept, but images \
                     sent to it will be refused"
                );
            }
        }
    }

    /// The default model's engine (sessions created without `model` get its descriptors).
    pub fn engine(&self) -> &Engine {
        &self.models[0]
    }

    /// The served model whose descriptors a session of descriptor space `id` holds.
    pub fn model_of(&self, id: &str) -> Option<&Engine> {
        self.models.iter().find(|e| e.info().compatible(id))
    }

    /// The default model's calibrated confidence.
    pub fn calibrator(&self) -> Option<&Arc<Calibrator>> {
        self.calibrators[0].as_ref()
    }

    /// The calibrated confidence of the served model whose descriptors a session of descriptor
    /// space `id` holds (None: not served here, or not calibrated).
    pub fn calibrator_of(&self, id: &str) -> Option<Arc<Calibrator>> {
        let i = self.models.iter().position(|e| e.info().compatible(id))?;
        self.calibrators[i].clone()
    }

    /// The served model called `name` (None or empty: the default).
    pub fn model_named(&self, name: Option<&str>) -> Result<&Engine, ApiError> {
        match name.filter(|n| !n.is_empty()) {
            None => Ok(self.engine()),
            Some(n) => self.models.iter().find(|e| e.info().name == n).ok_or_else(|| {
                ApiError::InvalidArgument(format!(
                    "model '{n}' is not served here (served: {}; GET /v1/models)",
                    self.models.iter().map(|e| e.info().name.as_str()).collect::<Vec<_>>().join(", ")
                ))
            }),
        }
    }

    /// "name (descriptor id), ..." of the served models, for messages.
    fn served_ids(&self) -> String {
        self.models
            .iter()
            .map(|e| format!("{} ({})", e.info().name, e.info().descriptor_id))
            .collect::<Vec<_>>()
            .join(", ")
    }

    pub async fn create_session(&self, req: CreateSession) -> Result<SessionInfo, ApiError> {
        let defaults = req.default_query.apply(&LoopQuery::default());
        defaults.validate().map_err(ApiError::from)?;
        if let Some(c) = &req.camera {
            c.intrinsics().validate().map_err(|e| ApiError::InvalidArgument(format!("camera: {e}")))?;
            if let Some(s) = c.depth_scale.filter(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(ApiError::InvalidArgument(format!("camera: depth_scale {s} must be a finite number > 0")));
            }
            // The pair checked once here (for a nominal image size), so a frame never meets a bad rig.
            if let Some(Err(e)) = c.stereo_rig(640, 480) {
                return Err(ApiError::InvalidArgument(format!("camera: {e}")));
            }
        }
        let model = self.model_named(req.model.as_deref())?;
        let descriptor_id = model.info().descriptor_id.clone();
        let dim = model.info().dim;
        let meta = self
            .store
            .create_session(
                req.id.filter(|s| !s.is_empty()),
                NewSession {
                    name: req.name,
                    dim,
                    descriptor_id,
                    storage: req.storage,
                    default_query: defaults,
                    camera: req.camera,
                    thumbnails: req.thumbnails,
                    index: req.index,
                    model: Some(model.info().name.clone()),
                },
            )
            .await?;
        Ok(self.store.session(&meta.id)?.info())
    }

    pub fn list_sessions(&self) -> Vec<SessionInfo> {
        self.store.list()
    }

    pub async fn delete_session(&self, id: &str) -> Result<(), ApiError> {
        Ok(self.store.delete_session(id).await?)
    }

    /// An image's unit descriptor under `variant` of the model called `model` (None: the
    /// default), with the id of its descriptor space.
    pub async fn embed(
        &self,
        image: Bytes,
        variant: Variant,
        model: Option<&str>,
    ) -> Result<(String, Vec<f32>), ApiError> {
        let engine = self.model_named(model)?;
        if !engine.info().has_variant(variant) {
            return Err(ApiError::InvalidArgument(format!(
                "model '{}' computes its whole output only: attention and fusion cannot be turned off",
                engine.info().name
            )));
        }
        let descriptor = engine.embed_image(image, variant).await?;
        Ok((engine.info().variant_id(variant).to_string(), descriptor))
    }

    /// A stored frame's header (searchable frames only).
    pub fn frame(&self, s: &Session, frame_id: u64) -> Result<FrameHeader, ApiError> {
        Ok(s.frame(frame_id)?.0)
    }

    /// The served model that embeds images for a session: the one of its descriptor space. A
    /// cluster node without it answers UNAVAILABLE / 503 (nodes are meant to serve the same
    /// models: another node, or this one once restarted with the model, can take the image); a
    /// server of its own answers FAILED_PRECONDITION / 409.
    pub fn engine_of(&self, s: &Session) -> Result<&Engine, ApiError> {
        self.model_of(&s.meta.descriptor_id).ok_or_else(|| {
            if self.store.is_shared() {
                return ApiError::Unavailable(format!(
                    "session '{}' is of model '{}' ({}), which this node does not serve (it serves {}): the \
                     cluster's nodes must serve the same models; send it to a node that serves '{}'",
                    s.meta.id,
                    s.meta.model.as_deref().unwrap_or("(the default of the server that made it)"),
                    s.meta.descriptor_id,
                    self.served_ids(),
                    s.meta.model.as_deref().unwrap_or("it"),
                ));
            }
            ApiError::FailedPrecondition(format!(
                "session '{}' holds descriptors of '{}', but this server computes {}: images sent to it \
                 would mix descriptor spaces (run a server with the session's model, or create a new session)",
                s.meta.id,
                s.meta.descriptor_id,
                self.served_ids()
            ))
        })
    }

    /// Images embedded here may only go to sessions of a served model's descriptor space.
    pub(super) fn check_space(&self, s: &Session) -> Result<(), ApiError> {
        self.engine_of(s).map(|_| ())
    }

    /// The descriptor of a frame's content and, for an image when `features` is asked for, its
    /// local features, extracted on the verification workers while the model embeds it (and
    /// its thumbnail, when `thumbnail` is asked for, on a blocking thread meanwhile).
    async fn prepare(
        &self,
        s: &Session,
        content: Content,
        features: bool,
        thumbnail: bool,
    ) -> Result<Prepared, ApiError> {
        let bytes = match content {
            Content::Descriptor(descriptor, space) => {
                if let Some(space) = space.filter(|id| *id != s.meta.descriptor_id) {
                    return Err(ApiError::FailedPrecondition(format!(
                        "session '{}' holds descriptors of '{}'{}, but this descriptor is of '{space}'{}: they \
                         would mix descriptor spaces",
                        s.meta.id,
                        s.meta.descriptor_id,
                        self.model_of(&s.meta.descriptor_id)
                            .map_or(String::new(), |e| format!(" (model {})", e.info().name)),
                        self.model_of(&space).map_or(String::new(), |e| format!(" (model {})", e.info().name)),
                    )));
                }
                let none = QueryFeatures::None("the query has no image (descriptor only)".into());
                return Ok(Prepared { descriptor, features: none, thumbnail: None });
            }
            Content::Embedded { descriptor, features } => {
                self.check_space(s)?;
                let features = match features {
                    Ok(f) => QueryFeatures::Some(Arc::new(f)),
                    Err(why) => QueryFeatures::None(why),
                };
                return Ok(Prepared { descriptor, features, thumbnail: None });
            }
            Content::Image { image, depth, right } => (image, depth, right),
        };
        let (bytes, depth, right) = bytes;
        if right.is_some() && depth.is_some() {
            return Err(ApiError::InvalidArgument("send a depth image or a right image, not both".into()));
        }
        if right.is_some() && s.meta.camera.as_ref().is_none_or(|c| c.stereo.is_none()) {
            return Err(ApiError::InvalidArgument(
                "a right image needs a session camera with stereo (baseline, or the right camera's pose)".into(),
            ));
        }
        let engine = self.engine_of(s)?;
        let scale = s.meta.camera.as_ref().map_or(crate::verify::depth::DEFAULT_DEPTH_SCALE, |c| c.depth_scale());
        // The engine's queue first: a refused image (overload) is neither decoded nor searched
        // for features, so a refusal stays cheap while the model is busy.
        let admission = engine.admit()?;
        let limits = engine.info().limits;
        // A depth image is decoded before anything else: a bad one is refused, nothing stored.
        let depth = match depth {
            Some(d) if features => Some(self.verifier.decode_depth(d, scale, limits).await.map_err(bad_depth)?),
            _ => None,
        };
        let embed = engine.embed_admitted(admission, bytes.clone(), Variant::FULL);
        let camera = s.meta.camera;
        let extract = async {
            match features {
                // The right image's features beside the left's, on another verification worker.
                true => match tokio::join!(
                    self.verifier.extract(bytes.clone(), limits, depth.is_some() || right.is_some()),
                    async {
                        match &right {
                            Some(r) => Some(self.verifier.extract(r.clone(), limits, false).await),
                            None => None,
                        }
                    }
                ) {
                    (Ok(mut f), right) => match (&depth, right, &camera) {
                        (Some(d), _, _) => d.attach(&mut f).map(|_| Ok(f)).map_err(bad_depth),
                        (None, Some(rf), Some(c)) => {
                            let rf = rf.map_err(bad_depth)?;
                            match c.stereo_rig(f.width, f.height).and_then(Result::ok) {
                                Some(rig) => rig.attach(&mut f, &rf).map(|_| Ok(f)).map_err(bad_depth),
                                None => Ok(Ok(f)),
                            }
                        }
                        _ => Ok(Ok(f)),
                    },
                    (Err(e), _) => Ok(Err(no_features(e))),
                },
                false => Ok(Err("feature extraction is off".to_string())),
            }
        };
        let (descriptor, extracted, thumbnail) =
            tokio::join!(embed, extract, make_thumbnail(&bytes, limits, thumbnail));
        let features = match extracted? {
            Ok(f) => QueryFeatures::Some(Arc::new(f)),
            Err(why) => QueryFeatures::None(why),
        };
        Ok(Prepared { descriptor: descriptor?, features, thumbnail })
    }

    /// Whether frames keep their local features (the server's setting).
    pub fn keeps_features(&self) -> bool {
        self.verifier.config().max_feature_bytes > 0
    }

    /// Adds a frame to the session the caller's scope looked up (`tenancy.rs`).
    pub async fn add_frame(&self, s: &Arc<Session>, mut f: FrameInput) -> Result<u64, ApiError> {
        // Every check that needs no forward pass; the descriptor space is checked in `prepare`,
        // before the image is embedded.
        let t = f.check()?;
        let content = std::mem::replace(&mut f.content, Content::Descriptor(Vec::new(), None));
        let prepared = self.prepare(s, content, self.keeps_features(), s.meta.thumbnails).await?;
        self.store_frame(s, f.into_new_frame(t, prepared)).await
    }

    async fn store_frame(&self, s: &Arc<Session>, frame: NewFrame) -> Result<u64, ApiError> {
        let ids = self.store.add_frames(s, vec![frame]).await?;
        ids.first().copied().ok_or_else(|| ApiError::Internal("no frame id returned".into()))
    }
}

/// A depth image the server cannot use: refused (400 / INVALID_ARGUMENT), nothing stored.
fn bad_depth(e: crate::verify::VerifyError) -> ApiError {
    ApiError::InvalidArgument(e.to_string())
}

/// Why a query has no features, as its answers say (the image still embeds: an image ORB cannot
/// use is answered unverified, not refused).
pub(crate) fn no_features(e: crate::verify::VerifyError) -> String {
    format!("no features: {e}")
}
