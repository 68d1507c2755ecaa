//! The service's searches: the store's best descriptor matches for a query, checked by
//! geometry and sequence and ranked by the one decision rule with their confidences (`query`,
//! `add_and_query`, and a frame's own query by id).
use super::*;

impl LoopService {
    /// The calibrator for a session's descriptors: its served model's.
    fn calibrator_for(&self, s: &Session) -> Option<Arc<Calibrator>> {
        self.calibrator_of(&s.meta.descriptor_id)
    }

    /// A query may ask for a minimum confidence only where confidences are calibrated.
    pub(in crate::api) fn check_confidence(&self, s: &Session, q: &LoopQuery) -> Result<(), ApiError> {
        if q.min_confidence > 0.0 && self.calibrator_for(s).is_none() {
            return Err(ApiError::FailedPrecondition(format!(
                "min_confidence needs a calibrated confidence, and this server has no calibrator for the \
                 descriptors of session '{}' ({}): leave it at 0 (or start the server with a calibration \
                 file that covers them)",
                s.meta.id, s.meta.descriptor_id
            )));
        }
        Ok(())
    }

    /// Ranked candidates: the store's best descriptor matches, the first K of them checked
    /// geometrically and all of them by sequence when the query asks for it, then ordered by the
    /// one decision rule, each with its confidence. Also the query's best matches by descriptor:
    /// its sequence votes.
    async fn search(
        &self,
        s: &Arc<Session>,
        descriptor: Vec<f32>,
        features: &QueryFeatures,
        history: History,
        q: &LoopQuery,
    ) -> Result<(Vec<LoopMatch>, Vec<u64>), ApiError> {
        // Unit length once, here: the search, the sequence votes and the query's own place in its
        // trail all read this one vector.
        let mut descriptor = descriptor;
        crate::index::normalize(&mut descriptor).map_err(crate::store::StoreError::from)?;
        let v = &q.verify;
        let wide = LoopQuery { k: verify::search_width(q), ..q.clone() };
        let query_descriptor = v.sequence.then(|| descriptor.clone());
        let mut matches = self.store.query(s, descriptor, &wide).await?;
        let votes = matches.iter().take(sequence::VOTES).map(|m| m.frame_id).collect();
        let calibrator = self.calibrator_for(s);
        let place = |(robot, position)| Place { robot, position };
        if !v.geometric && !v.sequence {
            let ids: Vec<u64> = matches.iter().map(|m| m.frame_id).collect();
            let places = s.places(&ids).into_iter().map(place).collect();
            let candidates = matches.into_iter().map(|m| (m, None)).collect();
            let mut plain = verify::check(None, candidates, &Checks::none(places, calibrator));
            plain.retain(|m| m.confidence.is_none_or(|c| c >= q.min_confidence));
            plain.truncate(q.k);
            return Ok((plain, votes));
        }
        if let Some(d) = &query_descriptor {
            // Where the robot's past says it is now, beside what looks most alike now.
            let stored = match &history {
                History::Stored(id) => Some(*id),
                History::Live(_) => None,
            };
            let have: Vec<u64> = matches.iter().map(|m| m.frame_id).collect();
            matches.extend(s.voted(d, q, stored, v.sequence_length.saturating_sub(1), &have));
        }
        let checked = if v.geometric { v.candidates.min(matches.len()) } else { 0 };
        let query = v.geometric.then(|| match features {
            QueryFeatures::Some(f) => Ok(f.clone()),
            QueryFeatures::None(why) => Err(why.clone()),
        });
        let ids: Vec<u64> = matches.iter().map(|m| m.frame_id).collect();
        let l = v.sequence_length;
        let (places, trails, tail) = s.trails(
            &ids,
            if v.sequence { l } else { 0 },
            match &history {
                History::Live(robot) if v.sequence => robot.as_deref(),
                _ => None,
            },
        );
        let places: Vec<Place> = places.into_iter().map(place).collect();
        let seq = query_descriptor.map(|query_descriptor| {
            let history = match &history {
                History::Stored(id) => s.trails(&[*id], l, None).1.pop().unwrap_or_default(),
                History::Live(_) => {
                    let mut tail = tail;
                    tail.drain(..tail.len().saturating_sub(l - 1));
                    tail.push(query_descriptor);
                    tail
                }
            };
            let stats = s.row_stats(&history, q);
            SequenceInputs {
                history,
                stats,
                trails,
                places: places.clone(),
                min_margin: v.min_sequence_margin,
                length: l,
            }
        });
        let mut candidates = Vec::with_capacity(matches.len());
        for (i, m) in matches.into_iter().enumerate() {
            let wanted = i < checked && matches!(query, Some(Ok(_)));
            let stored = if wanted { s.features(m.frame_id)? } else { None };
            let features = stored.and_then(|b| stored_features(&s.meta.id, m.frame_id, &b));
            candidates.push((m, features));
        }
        let camera = s.meta.camera.as_ref().map(Camera::intrinsics);
        let params = VerifyParams { min_inliers: v.min_inliers, ..Default::default() };
        let checks = Checks { checked, camera, params, seq, places, calibrator };
        let mut out = self.verifier.check(query, candidates, checks).await?;
        out.retain(|m| m.confidence.is_none_or(|c| c >= q.min_confidence));
        out.truncate(q.k);
        Ok((out, votes))
    }

    pub async fn query(
        &self,
        s: &Arc<Session>,
        robot_id: Option<String>,
        at_time: Option<f64>,
        target: QueryTarget,
        options: &QueryOverrides,
    ) -> Result<Vec<LoopMatch>, ApiError> {
        let mut q = options.apply(&s.meta.default_query);
        q.robot_id = robot_id.filter(|r| !r.is_empty());
        if let Some(r) = &q.robot_id {
            check_robot_id(r)?;
        }
        q.at_time = at_time;
        q.validate().map_err(ApiError::from)?;
        self.check_confidence(s, &q)?;
        match target {
            QueryTarget::Frame(id) => {
                let stored = s.features(id)?.and_then(|b| stored_features(&s.meta.id, id, &b));
                let features = match stored {
                    Some(f) => QueryFeatures::Some(Arc::new(f)),
                    None => QueryFeatures::None("the query frame has no stored features".into()),
                };
                let d = s.descriptor(id)?;
                let q = LoopQuery { exclude_frame: Some(id), ..q };
                let matches = self.search(s, d, &features, History::Stored(id), &q).await?.0;
                let (header, _) = s.frame(id)?;
                let asked = QueryFrame { id, robot: &header.robot_id, time: header.timestamp };
                self.keep_loops(s, asked, &matches).await;
                Ok(matches)
            }
            QueryTarget::Content(c) => {
                let p = self.prepare(s, c, q.verify.geometric, false).await?;
                let history = History::Live(q.robot_id.clone());
                Ok(self.search(s, p.descriptor, &p.features, history, &q).await?.0)
            }
        }
    }

    /// Queries with the new frame first (so it cannot match itself), then stores it.
    pub async fn add_and_query(
        &self,
        s: &Arc<Session>,
        mut f: FrameInput,
        options: &QueryOverrides,
    ) -> Result<(u64, Vec<LoopMatch>), ApiError> {
        let t = f.check()?;
        let mut q = options.apply(&s.meta.default_query);
        q.robot_id = Some(f.robot_id.clone());
        q.at_time = Some(t);
        // A retry of a write already stored: answered as the first write was, without itself.
        if let Some(id) = f.idempotency_key.as_deref().and_then(|k| s.frame_of_key(k)) {
            q.exclude_frame = Some(id);
        }
        q.validate().map_err(ApiError::from)?;
        self.check_confidence(s, &q)?;
        let content = std::mem::replace(&mut f.content, Content::Descriptor(Vec::new(), None));
        let features = q.verify.geometric || self.keeps_features();
        let prepared = self.prepare(s, content, features, s.meta.thumbnails).await?;
        let history = History::Live(Some(f.robot_id.clone()));
        let (matches, votes) = self.search(s, prepared.descriptor.clone(), &prepared.features, history, &q).await?;
        let prepared = if self.keeps_features() {
            prepared
        } else {
            Prepared { features: QueryFeatures::None(String::new()), ..prepared }
        };
        // The candidates answered are kept with the frame, in its flush.
        let robot = f.robot_id.clone();
        // Made for the batch's first frame: the store gives each its frame id.
        let keep =
            loop_records(QueryFrame { id: 0, robot: &robot, time: t }, &matches).into_iter().map(|l| (0, l)).collect();
        let ids = self.store.add_frames_keeping(s, vec![f.into_new_frame(t, prepared)], keep).await?;
        let id = ids.first().copied().ok_or_else(|| ApiError::Internal("no frame id returned".into()))?;
        // Its best matches by descriptor: the candidates it votes for in later sequence checks.
        s.set_votes(id, votes);
        Ok((id, matches))
    }
}

/// A frame's stored feature record, or None (logged) where it does not decode: that frame is
/// answered unverified rather than failing the query.
fn stored_features(session: &str, frame: u64, blob: &[u8]) -> Option<Features> {
    match Features::decode(blob) {
        Ok(f) => Some(f),
        Err(e) => {
            tracing::warn!(session, frame, error = %e, "stored features do not decode: the frame is not verified");
            None
        }
    }
}
