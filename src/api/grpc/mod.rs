//! gRPC (tonic): `proto/loopd/v1/loopd.proto` translated onto `LoopService`.
pub mod admin;
pub mod loops;

use crate::api::error::ApiError;
use crate::api::service::{Content, CreateSession, FrameInput, LoopMatch, LoopService, QueryOverrides, QueryTarget};
use crate::auth::{Auth, Caller};
use crate::index::graph::IndexKind;
use crate::index::query::{Pose, Scope};
use crate::index::Storage;
use crate::pb;
use crate::store::record::Camera;
use crate::store::SessionInfo;
use crate::verify::geometric::Verification;
use std::pin::Pin;
use std::sync::Arc;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

pub use pb::loopd_server::LoopdServer;

pub struct GrpcApi {
    pub service: LoopService,
    /// Turns true when the server shuts down: open frame streams end.
    pub shutdown: tokio::sync::watch::Receiver<bool>,
}

fn overrides(o: Option<pb::QueryOptions>) -> Result<QueryOverrides, ApiError> {
    let Some(o) = o else { return Ok(QueryOverrides::default()) };
    let scope = match pb::Scope::try_from(o.scope) {
        Ok(pb::Scope::Unspecified) => None,
        Ok(pb::Scope::All) => Some(Scope::All),
        Ok(pb::Scope::SameRobot) => Some(Scope::SameRobot),
        Ok(pb::Scope::OtherRobots) => Some(Scope::OtherRobots),
        Err(_) => return Err(ApiError::InvalidArgument(format!("unknown scope {}", o.scope))),
    };
    let pair = |a: Option<f64>, b: Option<f64>| {
        (a.is_some() || b.is_some()).then(|| (a.unwrap_or(f64::MIN), b.unwrap_or(f64::MAX)))
    };
    let ids = (o.frame_id_from.is_some() || o.frame_id_to.is_some())
        .then(|| (o.frame_id_from.unwrap_or(0), o.frame_id_to.unwrap_or(u64::MAX)));
    Ok(QueryOverrides {
        k: o.k.map(|k| k as usize),
        min_score: o.min_score,
        min_confidence: o.min_confidence,
        exclude_last_frames: o.exclude_last_frames.map(|n| n as usize),
        exclude_last_seconds: o.exclude_last_seconds,
        scope,
        time_range: pair(o.time_from, o.time_to),
        frame_id_range: ids,
        verify: o.verify,
        verify_candidates: o.verify_candidates.map(|k| k as usize),
        min_inliers: o.min_inliers.map(|n| n as usize),
        sequence: o.sequence,
        sequence_length: o.sequence_length.map(|n| n as usize),
        min_sequence_margin: o.min_sequence_margin,
    })
}

fn camera(c: Option<pb::Camera>) -> Result<Option<Camera>, ApiError> {
    let Some(c) = c else { return Ok(None) };
    let distortion = match c.distortion.as_slice() {
        [] => None,
        &[k1, k2, p1, p2, k3] => Some([k1, k2, p1, p2, k3]),
        d => return Err(ApiError::InvalidArgument(format!("camera distortion has {} values; 0 or 5", d.len()))),
    };
    let stereo = match c.stereo {
        None => None,
        Some(s) => {
            fn fixed<const N: usize>(v: &[f64], name: &str) -> Result<Option<[f64; N]>, ApiError> {
                match v.len() {
                    0 => Ok(None),
                    k if k == N => Ok(v.try_into().ok()),
                    k => Err(ApiError::InvalidArgument(format!("camera stereo {name} has {k} values; 0 or {N}"))),
                }
            }
            Some(crate::store::record::StereoCamera {
                baseline: s.baseline,
                rotation: fixed(&s.rotation, "rotation")?,
                translation: fixed(&s.translation, "translation")?,
                right_intrinsics: fixed(&s.right_intrinsics, "right_intrinsics")?,
                right_distortion: fixed(&s.right_distortion, "right_distortion")?,
            })
        }
    };
    Ok(Some(Camera { fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, distortion, depth_scale: c.depth_scale, stereo }))
}

/// An optional bytes field: empty is unset.
fn depth(b: bytes::Bytes) -> Option<bytes::Bytes> {
    (!b.is_empty()).then_some(b)
}

fn verification_to_pb(v: Verification) -> pb::Verification {
    pb::Verification {
        matches: v.matches as u32,
        inliers: v.inliers as u32,
        inlier_ratio: v.inlier_ratio,
        verified: v.verified,
        reason: v.reason.unwrap_or_default(),
        relative_pose: v.relative_pose.map(pb::RelativePose::from),
        metric: v.metric,
        covariance: v.covariance.unwrap_or_default(),
        pose_inliers: v.pose_inliers as u32,
    }
}

fn storage_to_pb(s: Storage) -> i32 {
    match s {
        Storage::F16 => pb::Storage::F16 as i32,
        Storage::F32 => pb::Storage::F32 as i32,
    }
}

fn session_to_pb(i: SessionInfo) -> pb::Session {
    pb::Session {
        id: i.meta.id,
        name: i.meta.name,
        created: i.meta.created,
        dim: i.meta.dim as u32,
        descriptor_id: i.meta.descriptor_id,
        storage: storage_to_pb(i.meta.storage),
        frames: i.frames as u64,
        robots: i.robots,
        bytes_on_disk: i.bytes_on_disk,
        thumbnails: i.meta.thumbnails,
        index: match i.meta.index {
            IndexKind::Auto => pb::IndexKind::Auto,
            IndexKind::Exact => pb::IndexKind::Exact,
            IndexKind::Approximate => pb::IndexKind::Approximate,
        } as i32,
        approximate_frames: i.approximate_frames.map(|n| n as u64),
        model: i.meta.model.unwrap_or_default(),
    }
}

fn matches_to_pb(m: Vec<LoopMatch>) -> Vec<pb::Match> {
    m.into_iter()
        .map(|LoopMatch { m, verification, sequence, confidence, .. }| pb::Match {
            frame_id: m.frame_id,
            score: m.score,
            robot_id: m.robot_id,
            timestamp: m.timestamp,
            pose: m.pose.map(pb::Pose::from),
            verification: verification.map(verification_to_pb),
            sequence: sequence.map(|s| pb::SequenceCheck {
                score: s.score,
                margin: s.margin,
                length: s.length as u32,
                verified: s.verified,
            }),
            confidence,
        })
        .collect()
}

/// An AddFrame request's bytes as the gRPC API reads them: decoded, converted and validated
/// (the fuzz target's entry; tonic decodes with the same prost code).
pub fn parse_add_frame(bytes: &[u8]) -> Result<(String, FrameInput, QueryOverrides), ApiError> {
    let r = <pb::AddFrameRequest as prost::Message>::decode(bytes)
        .map_err(|e| ApiError::InvalidArgument(format!("not an AddFrameRequest: {e}")))?;
    let (session, f, opts) = frame_input(r)?;
    f.validate(&opts)?;
    Ok((session, f, opts))
}

fn frame_input(r: pb::AddFrameRequest) -> Result<(String, FrameInput, QueryOverrides), ApiError> {
    let content = match r.content {
        Some(pb::add_frame_request::Content::Image(b)) => {
            Content::Image { image: b, depth: depth(r.depth), right: depth(r.right) }
        }
        Some(pb::add_frame_request::Content::Descriptor(_)) if !r.depth.is_empty() || !r.right.is_empty() => {
            return Err(ApiError::InvalidArgument("a depth or right image goes with an image, not a descriptor".into()))
        }
        Some(pb::add_frame_request::Content::Descriptor(d)) => {
            Content::Descriptor(d.values, Some(d.descriptor_id).filter(|i| !i.is_empty()))
        }
        None => return Err(ApiError::InvalidArgument("a frame needs an image or a descriptor".into())),
    };
    let metadata = if r.metadata_json.is_empty() {
        None
    } else {
        Some(
            serde_json::from_str(&r.metadata_json)
                .map_err(|e| ApiError::InvalidArgument(format!("metadata_json: {e}")))?,
        )
    };
    if r.session_id.is_empty() {
        return Err(ApiError::InvalidArgument("session_id is required".into()));
    }
    let opts = overrides(r.options)?;
    let f = FrameInput {
        robot_id: r.robot_id,
        timestamp: r.timestamp,
        frame_id: r.frame_id,
        pose: r.pose.map(Pose::from),
        metadata,
        content,
        thumbnail: None,
        idempotency_key: (!r.idempotency_key.is_empty()).then_some(r.idempotency_key),
    };
    Ok((r.session_id, f, opts))
}

/// The caller the authentication interceptor put on the request (see `server.rs`).
pub(super) fn caller<T>(req: &Request<T>) -> Result<Caller, Status> {
    req.extensions()
        .get::<Caller>()
        .cloned()
        .ok_or_else(|| Status::unauthenticated("no caller: request not authenticated"))
}

/// The gRPC interceptor: the key in the `authorization` metadata (`Bearer <key>`) names the
/// caller; the health service stays open (it is not intercepted).
pub fn authenticate(auth: Arc<Auth>) -> impl Fn(Request<()>) -> Result<Request<()>, Status> + Clone {
    move |mut req: Request<()>| {
        let header = req.metadata().get("authorization").map(|v| v.as_bytes());
        let caller = auth.authenticate(header).map_err(ApiError::from)?;
        req.extensions_mut().insert(caller);
        Ok(req)
    }
}

type FrameStream = Pin<Box<dyn Stream<Item = Result<pb::AddAndQueryResponse, Status>> + Send>>;

#[tonic::async_trait]
impl pb::loopd_server::Loopd for GrpcApi {
    async fn create_session(&self, req: Request<pb::CreateSessionRequest>) -> Result<Response<pb::Session>, Status> {
        let caller = caller(&req)?;
        let r = req.into_inner();
        let storage = match pb::Storage::try_from(r.storage) {
            Ok(pb::Storage::F32) => Storage::F32,
            Ok(_) => Storage::F16,
            Err(_) => return Err(Status::invalid_argument(format!("unknown storage {}", r.storage))),
        };
        let index = match pb::IndexKind::try_from(r.index) {
            Ok(pb::IndexKind::Auto) => IndexKind::Auto,
            Ok(pb::IndexKind::Exact) => IndexKind::Exact,
            Ok(pb::IndexKind::Approximate) => IndexKind::Approximate,
            Err(_) => return Err(Status::invalid_argument(format!("unknown index kind {}", r.index))),
        };
        let create = CreateSession {
            id: Some(r.id),
            name: r.name,
            storage,
            default_query: overrides(r.default_query)?,
            camera: camera(r.camera)?,
            thumbnails: r.thumbnails,
            index,
            model: Some(r.model).filter(|m| !m.is_empty()),
        };
        Ok(Response::new(session_to_pb(self.service.scoped(caller).create_session(create).await?)))
    }

    async fn get_session(&self, req: Request<pb::GetSessionRequest>) -> Result<Response<pb::Session>, Status> {
        let caller = caller(&req)?;
        Ok(Response::new(session_to_pb(self.service.scoped(caller).session(&req.into_inner().id).await?)))
    }

    async fn list_sessions(
        &self,
        req: Request<pb::ListSessionsRequest>,
    ) -> Result<Response<pb::ListSessionsResponse>, Status> {
        let caller = caller(&req)?;
        Ok(Response::new(pb::ListSessionsResponse {
            sessions: self.service.scoped(caller).list_sessions().await?.into_iter().map(session_to_pb).collect(),
        }))
    }

    async fn delete_session(
        &self,
        req: Request<pb::DeleteSessionRequest>,
    ) -> Result<Response<pb::DeleteSessionResponse>, Status> {
        let caller = caller(&req)?;
        self.service.scoped(caller).delete_session(&req.into_inner().id).await?;
        Ok(Response::new(pb::DeleteSessionResponse {}))
    }

    async fn add_frame(&self, req: Request<pb::AddFrameRequest>) -> Result<Response<pb::AddFrameResponse>, Status> {
        let caller = caller(&req)?;
        let (session, f, _) = frame_input(req.into_inner())?;
        Ok(Response::new(pb::AddFrameResponse { frame_id: self.service.scoped(caller).add_frame(&session, f).await? }))
    }

    async fn query(&self, req: Request<pb::QueryRequest>) -> Result<Response<pb::QueryResponse>, Status> {
        let caller = caller(&req)?;
        let r = req.into_inner();
        let target = match r.content {
            Some(pb::query_request::Content::Image(b)) => {
                QueryTarget::Content(Content::Image { image: b, depth: depth(r.depth), right: depth(r.right) })
            }
            Some(_) if !r.depth.is_empty() || !r.right.is_empty() => {
                return Err(ApiError::InvalidArgument("a depth or right image goes with an image".into()).into())
            }
            Some(pb::query_request::Content::Descriptor(d)) => {
                QueryTarget::Content(Content::Descriptor(d.values, Some(d.descriptor_id).filter(|i| !i.is_empty())))
            }
            Some(pb::query_request::Content::FrameId(id)) => QueryTarget::Frame(id),
            None => return Err(Status::invalid_argument("a query needs an image, a descriptor or a frame_id")),
        };
        let opts = overrides(r.options)?;
        let scoped = self.service.scoped(caller);
        let answer = scoped.query(&r.session_id, Some(r.robot_id), r.timestamp, target, &opts);
        let (m, stale) = crate::store::tracking_staleness(answer).await;
        let mut response = Response::new(pb::QueryResponse { matches: matches_to_pb(m?) });
        if stale {
            // The node's index answered without the log's version (no writable primary).
            response.metadata_mut().insert("loopd-stale", tonic::metadata::MetadataValue::from_static("1"));
        }
        Ok(response)
    }

    async fn add_and_query(
        &self,
        req: Request<pb::AddFrameRequest>,
    ) -> Result<Response<pb::AddAndQueryResponse>, Status> {
        let caller = caller(&req)?;
        let (session, f, opts) = frame_input(req.into_inner())?;
        let (frame_id, m) = self.service.scoped(caller).add_and_query(&session, f, &opts).await?;
        Ok(Response::new(pb::AddAndQueryResponse { frame_id, matches: matches_to_pb(m), ..Default::default() }))
    }

    async fn list_loops(&self, req: Request<pb::ListLoopsRequest>) -> Result<Response<pb::ListLoopsResponse>, Status> {
        let caller = caller(&req)?;
        Ok(Response::new(loops::list(&self.service, caller, req.into_inner()).await?))
    }

    async fn set_loop_verdict(&self, req: Request<pb::SetLoopVerdictRequest>) -> Result<Response<pb::Loop>, Status> {
        let caller = caller(&req)?;
        Ok(Response::new(loops::set_verdict(&self.service, caller, req.into_inner()).await?))
    }

    async fn get_thumbnail(&self, req: Request<pb::GetThumbnailRequest>) -> Result<Response<pb::Thumbnail>, Status> {
        let caller = caller(&req)?;
        let r = req.into_inner();
        let jpeg = self.service.scoped(caller).thumbnail(&r.session_id, r.frame_id).await?;
        Ok(Response::new(pb::Thumbnail { jpeg: jpeg.into() }))
    }

    async fn list_models(
        &self,
        req: Request<pb::ListModelsRequest>,
    ) -> Result<Response<pb::ListModelsResponse>, Status> {
        caller(&req)?;
        let models = self
            .service
            .models
            .iter()
            .enumerate()
            .map(|(n, e)| {
                let i = e.info();
                let (input_width, input_height) = i.input.size();
                pb::Model {
                    name: i.name.clone(),
                    kind: i.about.kind.into(),
                    default: n == 0,
                    descriptor_id: i.descriptor_id.clone(),
                    dim: i.dim as u32,
                    input_width,
                    input_height,
                    device: i.device.clone(),
                    license: i.about.license.clone(),
                    source: i.about.source.clone(),
                }
            })
            .collect();
        Ok(Response::new(pb::ListModelsResponse { models }))
    }

    type StreamFramesStream = FrameStream;

    async fn stream_frames(
        &self,
        req: Request<Streaming<pb::AddFrameRequest>>,
    ) -> Result<Response<FrameStream>, Status> {
        let caller = caller(&req)?;
        let mut inbound = req.into_inner();
        let service = self.service.clone();
        let mut shutdown = self.shutdown.clone();
        let (tx, rx) = tokio::sync::mpsc::channel(16);
        tokio::spawn(async move {
            // In order, one frame at a time: each answer refers to the map as it was just before.
            loop {
                // A frame in hand is finished (stored, answered) before the stream ends.
                let next = tokio::select! {
                    biased;
                    // The watch guard is dropped inside: it must not live across the send below.
                    _ = async { shutdown.wait_for(|s| *s).await.is_ok() } => {
                        let _ = tx.send(Err(Status::unavailable("server shutting down: reconnect and resend unacknowledged frames"))).await;
                        break;
                    }
                    next = inbound.next() => match next {
                        Some(next) => next,
                        None => break,
                    },
                };
                let reply = match next {
                    Err(status) => {
                        tracing::debug!(%status, "client stream ended with an error");
                        break;
                    }
                    Ok(r) => match frame_input(r) {
                        Err(e) => failed(e),
                        Ok((session, f, opts)) => {
                            match service.scoped(caller.clone()).add_and_query(&session, f, &opts).await {
                                Ok((frame_id, m)) => pb::AddAndQueryResponse {
                                    frame_id,
                                    matches: matches_to_pb(m),
                                    ..Default::default()
                                },
                                Err(e) => failed(e),
                            }
                        }
                    },
                };
                if tx.send(Ok(reply)).await.is_err() {
                    break; // the robot hung up
                }
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }
}

fn failed(e: ApiError) -> pb::AddAndQueryResponse {
    let s = e.grpc_status();
    pb::AddAndQueryResponse { error_code: s.code() as i32, error: s.message().to_string(), ..Default::default() }
}
