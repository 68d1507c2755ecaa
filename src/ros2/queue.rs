//! A robot's keyframes waiting for the server: bounded, oldest dropped first (a camera callback
//! never waits), the frame being sent kept at the head until the server acknowledges it.
use std::collections::VecDeque;
use std::sync::Arc;

use crate::index::query::Pose;

/// A keyframe as the server will get it.
#[derive(Debug)]
pub struct Keyframe {
    /// The topic it came from.
    pub topic: String,
    /// Header stamp.
    pub stamp: super::msgs::Time,
    /// The camera's frame name (header.frame_id).
    pub camera_frame: String,
    /// JPEG or PNG as sent (compressed), a lossless PNG (raw); shared by every resend.
    pub image: bytes::Bytes,
    pub pose: Option<Pose>,
}

#[derive(Debug)]
pub struct Queue {
    cap: usize,
    frames: VecDeque<Arc<Keyframe>>,
    /// The head is being sent: it is not dropped to make room.
    head_in_flight: bool,
}

impl Queue {
    pub fn new(cap: usize) -> Self {
        Self { cap: cap.max(1), frames: VecDeque::new(), head_in_flight: false }
    }

    /// Adds a keyframe; returns the one dropped to make room, if any.
    pub fn push(&mut self, k: Keyframe) -> Option<Arc<Keyframe>> {
        let mut dropped = None;
        if self.frames.len() >= self.cap {
            // The oldest that is not on its way; with a queue of one in flight, the new one waits
            // beside it (cap + 1 at most).
            let i = usize::from(self.head_in_flight);
            dropped = self.frames.remove(i);
        }
        self.frames.push_back(Arc::new(k));
        dropped
    }

    /// The next keyframe to send (the head), marked in flight.
    pub fn head(&mut self) -> Option<Arc<Keyframe>> {
        let k = self.frames.front().cloned();
        self.head_in_flight = k.is_some();
        k
    }

    /// The head is done (acknowledged, or refused for good).
    pub fn done(&mut self, k: &Arc<Keyframe>) {
        if self.frames.front().is_some_and(|h| Arc::ptr_eq(h, k)) {
            self.frames.pop_front();
        }
        self.head_in_flight = false;
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kf(sec: i32) -> Keyframe {
        Keyframe {
            topic: "/r1/camera/image_raw".into(),
            stamp: super::super::msgs::Time { sec, nanosec: 0 },
            camera_frame: String::new(),
            image: bytes::Bytes::new(),
            pose: None,
        }
    }

    #[test]
    fn the_oldest_waiting_frame_is_dropped_never_the_one_in_flight() {
        let mut q = Queue::new(3);
        for s in 0..3 {
            assert!(q.push(kf(s)).is_none());
        }
        // Nothing in flight: the oldest goes.
        assert_eq!(q.push(kf(3)).unwrap().stamp.sec, 0);
        let head = q.head().unwrap();
        assert_eq!(head.stamp.sec, 1);
        // In flight: the next oldest goes, the head stays until it is acknowledged.
        assert_eq!(q.push(kf(4)).unwrap().stamp.sec, 2);
        assert_eq!(q.head().unwrap().stamp.sec, 1, "resent after a failure: the same head");
        q.done(&head);
        let order: Vec<i32> = std::iter::from_fn(|| {
            let k = q.head()?;
            q.done(&k);
            Some(k.stamp.sec)
        })
        .collect();
        assert_eq!(order, [3, 4]);
        assert!(q.is_empty());
    }
}
