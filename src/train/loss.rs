//! Multi-similarity loss with its pair mining (Wang et al., CVPR 2019), on masks so that
//! pairs within the ground-truth tolerance are neither positives nor negatives.
use tch::{Kind, Tensor};

#[derive(Clone, Copy, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
pub struct MsParams {
    /// Weight of positive pairs' soft-min.
    pub alpha: f64,
    /// Weight of negative pairs' soft-max.
    pub beta: f64,
    /// Similarity margin both sides are pushed away from.
    pub lambda: f64,
    /// Mining margin: a negative counts when it is within epsilon of the hardest positive.
    pub epsilon: f64,
}

impl Default for MsParams {
    fn default() -> Self {
        // The paper's (and pytorch-metric-learning's) values for cosine similarity.
        Self { alpha: 2.0, beta: 50.0, lambda: 0.5, epsilon: 0.1 }
    }
}

/// `d`: [B, D] unit descriptors; `pos`, `neg`: [B, B] 0/1 float masks (no diagonal in `pos`).
/// Returns the mean loss over anchors (a scalar that carries gradients to `d`).
pub fn multi_similarity(d: &Tensor, pos: &Tensor, neg: &Tensor, p: &MsParams) -> Tensor {
    let s = d.matmul(&d.tr());
    let big: f64 = 1e4;
    // Mining uses the similarities as constants: which pairs count is not differentiated.
    let (hardest_pos, hardest_neg) = tch::no_grad(|| {
        let sd = s.detach();
        let min_pos = (&sd + (1.0f64 - pos) * big).amin([1i64].as_slice(), true);
        let max_neg = (&sd - (1.0f64 - neg) * big).amax([1i64].as_slice(), true);
        let pos_keep = pos * (&sd - p.epsilon).lt_tensor(&max_neg).to_kind(Kind::Float);
        let neg_keep = neg * (&sd + p.epsilon).gt_tensor(&min_pos).to_kind(Kind::Float);
        (pos_keep, neg_keep)
    });
    let pos_term = (hardest_pos * (-(&s - p.lambda) * p.alpha).exp()).sum_dim_intlist([1i64].as_slice(), false, None);
    let neg_term = (hardest_neg * ((&s - p.lambda) * p.beta).exp()).sum_dim_intlist([1i64].as_slice(), false, None);
    (pos_term.log1p() / p.alpha + neg_term.log1p() / p.beta).mean(Kind::Float)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn masks(places: &[i64]) -> (Tensor, Tensor) {
        let l = Tensor::from_slice(places);
        let same = l.unsqueeze(1).eq_tensor(&l.unsqueeze(0)).to_kind(Kind::Float);
        let eye = Tensor::eye(places.len() as i64, (Kind::Float, tch::Device::Cpu));
        (&same - eye, 1.0 - same)
    }

    /// Hand-worked: two places, two views each, 2-d descriptors.
    #[test]
    fn matches_a_hand_computed_value() {
        let c = (0.6f64).sqrt();
        let s = (0.4f64).sqrt();
        // A0=(1,0) A1=(c,s) B0=(0,1) B1=(s,c): sim(A0,A1)=c, sim(A0,B0)=0, sim(A0,B1)=s, ...
        let d = Tensor::from_slice(&[1.0f32, 0.0, c as f32, s as f32, 0.0, 1.0, s as f32, c as f32]).reshape([4, 2]);
        let (pos, neg) = masks(&[0, 0, 1, 1]);
        let p = MsParams::default();
        let got = f64::try_from(multi_similarity(&d, &pos, &neg, &p)).unwrap();
        // Anchor A0: positive c=0.775 (kept: c - 0.1 < max neg s=0.632? no -> dropped);
        // negatives 0 and s: kept when > min_pos - eps = 0.675 -> none: loss 0 (B0 mirrors A0).
        // Anchor A1 (B1 mirrors it): positive c, negatives sim(A1,B0)=s=0.632, sim(A1,B1)=2cs=0.980.
        let a1 = {
            let max_neg = 2.0 * c * s;
            let pos = if c - 0.1 < max_neg { (1.0 + (-2.0 * (c - 0.5)).exp()).ln() / 2.0 } else { 0.0 };
            let negs: f64 = [s, 2.0 * c * s].iter().filter(|&&v| v + 0.1 > c).map(|v| (50.0 * (v - 0.5)).exp()).sum();
            pos + (1.0 + negs).ln() / 50.0
        };
        let expected = (0.0 + a1 + 0.0 + a1) / 4.0;
        assert!((got - expected).abs() < 1e-5, "loss {got}, expected {expected}");
    }

    #[test]
    fn separated_places_cost_nothing_and_mixed_ones_cost_more() {
        let p = MsParams::default();
        let (pos, neg) = masks(&[0, 0, 1, 1]);
        let apart = Tensor::from_slice(&[1.0f32, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1.0]).reshape([4, 2]);
        assert_eq!(f64::try_from(multi_similarity(&apart, &pos, &neg, &p)).unwrap(), 0.0);
        let mixed = Tensor::from_slice(&[1.0f32, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0]).reshape([4, 2]);
        assert!(f64::try_from(multi_similarity(&mixed, &pos, &neg, &p)).unwrap() > 0.4);
    }
}
