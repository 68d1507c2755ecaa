//! P places x K views per batch, in a seeded order that a resumed run repeats.
use super::data::TrainSet;
use rand::seq::SliceRandom;
use rand::{rngs::StdRng, Rng, SeedableRng};
use tch::{Kind, Tensor};

/// One batch: sample indices (P x K, place-major) and the loss masks.
pub struct Batch {
    pub samples: Vec<usize>,
    /// Per entry: whether its view is an augmentation of the image (unlabelled place, or a
    /// second draw of a place with fewer than K images).
    pub augment: Vec<bool>,
    pub pos: Tensor,
    pub neg: Tensor,
}

/// The batches of one epoch: every place with two or more views (or augmented) once, in a
/// shuffled order fixed by (seed, epoch).
pub fn epoch_batches(set: &TrainSet, p: usize, k: usize, seed: u64, epoch: usize, rng_out: &mut StdRng) -> Vec<Batch> {
    let mut rng = StdRng::seed_from_u64(seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut order: Vec<usize> = (0..set.places.len()).collect();
    order.shuffle(&mut rng);
    let batches = order
        .chunks(p)
        .filter(|c| c.len() >= 2.min(p))
        .map(|places| {
            let mut samples = Vec::with_capacity(places.len() * k);
            let mut augment = Vec::with_capacity(places.len() * k);
            for &pl in places {
                let place = &set.places[pl];
                let mut members = place.samples.clone();
                members.shuffle(&mut rng);
                for v in 0..k {
                    samples.push(members[v % members.len()]);
                    augment.push(place.augmented || v >= members.len());
                }
            }
            let n = samples.len();
            let mut pos = vec![0f32; n * n];
            let mut neg = vec![0f32; n * n];
            for i in 0..n {
                for j in 0..n {
                    if i != j && set.samples[samples[i]].place == set.samples[samples[j]].place {
                        pos[i * n + j] = 1.0;
                    } else if set.negative(samples[i], samples[j]) {
                        neg[i * n + j] = 1.0;
                    }
                }
            }
            let mask = |v: Vec<f32>| Tensor::from_slice(&v).reshape([n as i64, n as i64]).to_kind(Kind::Float);
            Batch { samples, augment, pos: mask(pos), neg: mask(neg) }
        })
        .collect();
    *rng_out = StdRng::seed_from_u64(rng.random());
    batches
}
