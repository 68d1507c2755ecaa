//! What one search keeps: the rows a query may see (its filters resolved once to row tests) and
//! the best k of them, in an order that does not depend on which search thread saw a row first.
use super::*;

/// The query's filters, resolved once to row-level tests.
pub(super) struct Filter<'a> {
    index: &'a SessionIndex,
    robot: Option<u32>,
    scope: Scope,
    /// The querying robot's frames with this id or higher are excluded.
    exclude_from_id: Option<u64>,
    exclude_after_time: Option<f64>,
    time_range: Option<(f64, f64)>,
    frame_id_range: Option<(u64, u64)>,
    exclude_frame: Option<u64>,
}

impl<'a> Filter<'a> {
    pub(super) fn new(index: &'a SessionIndex, q: &LoopQuery) -> Self {
        let robot = q.robot_id.as_deref().and_then(|r| index.robot_ids.get(r).copied());
        let own_ids = robot.map(|r| index.by_robot[r as usize].as_slice()).unwrap_or(&[]);
        let exclude_from_id = (q.exclude_last_frames > 0 && !own_ids.is_empty())
            .then(|| own_ids[own_ids.len().saturating_sub(q.exclude_last_frames)]);
        let newest_own =
            own_ids.iter().map(|id| index.frames[index.by_frame[id]].timestamp).fold(f64::NEG_INFINITY, f64::max);
        let exclude_after_time = (q.exclude_last_seconds > 0.0 && robot.is_some())
            .then(|| q.at_time.unwrap_or(newest_own) - q.exclude_last_seconds);
        Self {
            index,
            robot,
            scope: q.scope,
            exclude_from_id,
            exclude_after_time,
            time_range: q.time_range,
            frame_id_range: q.frame_id_range,
            exclude_frame: q.exclude_frame,
        }
    }

    pub(super) fn allows(&self, row: usize) -> bool {
        let f = &self.index.frames[row];
        let own = self.robot == Some(f.robot);
        match self.scope {
            Scope::All => {}
            // An unknown querying robot has no own frames: same-robot matches nothing.
            Scope::SameRobot if !own => return false,
            Scope::OtherRobots if own => return false,
            _ => {}
        }
        if own {
            if self.exclude_from_id.is_some_and(|id| f.frame_id >= id) {
                return false;
            }
            if self.exclude_after_time.is_some_and(|t| f.timestamp > t) {
                return false;
            }
        }
        if self.time_range.is_some_and(|(a, b)| f.timestamp < a || f.timestamp > b) {
            return false;
        }
        if self.frame_id_range.is_some_and(|(a, b)| f.frame_id < a || f.frame_id > b) {
            return false;
        }
        self.exclude_frame != Some(f.frame_id)
    }
}

/// Bounded min-heap of the best (score, row). Of equal scores the earlier row ranks higher, in
/// every order rows arrive in, so results do not depend on which search thread saw a row first.
pub(super) struct TopK {
    k: usize,
    heap: BinaryHeap<Reverse<RankKey>>,
}

/// Higher ranks first: a better score, then an earlier row.
pub(super) type RankKey = (OrderedFloat<f32>, Reverse<usize>);

pub(super) fn rank_key(score: f32, row: usize) -> RankKey {
    (OrderedFloat(score), Reverse(row))
}

impl TopK {
    pub(super) fn new(k: usize) -> Self {
        Self { k, heap: BinaryHeap::with_capacity(k + 1) }
    }

    pub(super) fn would_take(&self, score: f32, row: usize) -> bool {
        self.heap.len() < self.k || self.heap.peek().is_some_and(|m| rank_key(score, row) > m.0)
    }

    pub(super) fn push(&mut self, score: f32, row: usize) {
        if !self.would_take(score, row) {
            return;
        }
        self.heap.push(Reverse(rank_key(score, row)));
        if self.heap.len() > self.k {
            self.heap.pop();
        }
    }

    pub(super) fn merge(&mut self, other: TopK) {
        for Reverse((score, Reverse(row))) in other.heap {
            self.push(score.0, row);
        }
    }

    /// Best first.
    pub(super) fn sorted(self) -> Vec<(f32, usize)> {
        self.heap.into_sorted_vec().into_iter().map(|Reverse((score, Reverse(row)))| (score.0, row)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::TopK;

    /// Equal scores keep the earlier rows whatever the arrival order (as with several threads).
    #[test]
    fn ties_keep_the_earlier_rows_in_any_arrival_order() {
        let mut late_first = TopK::new(2);
        for row in [9, 7, 3, 5, 1] {
            late_first.push(0.5, row);
        }
        assert_eq!(late_first.sorted(), vec![(0.5, 1), (0.5, 3)]);
        // Two workers' heaps merged, the one holding later rows first.
        let (mut a, mut b) = (TopK::new(2), TopK::new(2));
        [8, 9].into_iter().for_each(|r| a.push(0.5, r));
        [0, 1].into_iter().for_each(|r| b.push(0.5, r));
        let mut merged = TopK::new(2);
        merged.merge(a);
        merged.merge(b);
        assert_eq!(merged.sorted(), vec![(0.5, 0), (0.5, 1)]);
        let mut mixed = TopK::new(3);
        [(0.1, 0), (0.9, 4), (0.5, 2), (0.9, 3)].into_iter().for_each(|(s, r)| mixed.push(s, r));
        assert_eq!(mixed.sorted(), vec![(0.9, 3), (0.9, 4), (0.5, 2)]);
    }
}
