//! Which camera messages become keyframes: every Nth, at least a time step apart (header stamps)
//! and, where the robot's pose is known, at least a distance apart; an image with the stamp of
//! the last keyframe is that keyframe again. One selector per camera topic.
use crate::index::query::Pose;

#[derive(Clone, Copy, Debug)]
pub struct Rule {
    /// Every Nth message of a robot is considered (1: all).
    pub every: u64,
    /// Smallest step between keyframes, seconds of header stamp.
    pub min_dt: f64,
    /// Smallest distance between keyframes, metres (0: off); needs the robot's pose.
    pub min_distance: f64,
}

impl Default for Rule {
    fn default() -> Self {
        Self { every: 1, min_dt: 0.0, min_distance: 0.0 }
    }
}

#[derive(Debug, Default)]
pub struct Selector {
    seen: u64,
    last: Option<(f64, Option<Pose>)>,
}

impl Selector {
    /// Whether the message (stamp, pose at it) is a keyframe; a keyframe is remembered.
    pub fn take(&mut self, rule: &Rule, stamp: f64, pose: Option<&Pose>) -> bool {
        let n = self.seen;
        self.seen += 1;
        if !n.is_multiple_of(rule.every.max(1)) {
            return false;
        }
        if let Some((t, last_pose)) = &self.last {
            // A stamp before the last keyframe's: the robot's clock started again (a restarted
            // driver, a bag played in a loop); it starts a new run of keyframes.
            // The same stamp again is the same image (published again, or delivered twice).
            if stamp == *t {
                return false;
            }
            if stamp > *t {
                if stamp - t < rule.min_dt {
                    return false;
                }
                if rule.min_distance > 0.0 {
                    if let (Some(a), Some(b)) = (last_pose, pose) {
                        let d = ((a.x - b.x).powi(2) + (a.y - b.y).powi(2) + (a.z - b.z).powi(2)).sqrt();
                        if d < rule.min_distance {
                            return false;
                        }
                    }
                }
            }
        }
        self.last = Some((stamp, pose.copied()));
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64) -> Pose {
        Pose { x, y: 0.0, z: 0.0, qx: 0.0, qy: 0.0, qz: 0.0, qw: 1.0 }
    }

    #[test]
    fn every_nth_then_time_then_distance() {
        let rule = Rule { every: 2, ..Rule::default() };
        let mut s = Selector::default();
        let kept: Vec<bool> = (0..6).map(|i| s.take(&rule, i as f64, None)).collect();
        assert_eq!(kept, [true, false, true, false, true, false]);

        let rule = Rule { min_dt: 1.0, ..Rule::default() };
        let mut s = Selector::default();
        let kept: Vec<bool> = [0.0, 0.4, 0.9, 1.0, 1.5, 2.2].iter().map(|t| s.take(&rule, *t, None)).collect();
        assert_eq!(kept, [true, false, false, true, false, true]);

        let rule = Rule { min_distance: 0.5, ..Rule::default() };
        let mut s = Selector::default();
        let kept: Vec<bool> =
            [0.0, 0.2, 0.6, 0.7, 1.2].iter().enumerate().map(|(i, x)| s.take(&rule, i as f64, Some(&at(*x)))).collect();
        assert_eq!(kept, [true, false, true, false, true]);
        // Without a pose the distance cannot hold a frame back.
        assert!(s.take(&rule, 9.0, None));
    }

    #[test]
    fn a_clock_that_starts_again_starts_a_new_run() {
        let rule = Rule { min_dt: 5.0, ..Rule::default() };
        let mut s = Selector::default();
        assert!(s.take(&rule, 100.0, None));
        assert!(!s.take(&rule, 101.0, None));
        assert!(s.take(&rule, 3.0, None), "a stamp before the last keyframe's");
        assert!(!s.take(&rule, 4.0, None));
    }

    #[test]
    fn the_same_stamp_again_is_not_a_new_keyframe() {
        let mut s = Selector::default();
        assert!(s.take(&Rule::default(), 7.0, None));
        assert!(!s.take(&Rule::default(), 7.0, None));
        assert!(s.take(&Rule::default(), 7.5, None));
    }
}
