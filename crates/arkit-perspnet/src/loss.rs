//! PerspNet training losses, following the official `models/loss.py` `Loss8`
//! (the one `face_pose_uvluv_model.py` trains with).
//!
//! * `L_corr`: smooth L1 (threshold 0.01, summed over xyz, mean over points) between
//!   `softmax(A) (X / 9 * 4.5)` and the ground-truth coordinates at the chosen pixels
//!   (`nocs`), where X are the vertices read from the predicted UV map.
//! * `L_S`: L1 (mean) between X and `9 x` the canonical mesh.
//! * `L_KL`: `KL(target || softmax(A))` summed and divided by `B x M`.
//! * entropy: `0.001 x` mean per-point entropy of `softmax(A)`.
//! * `L_seg`: 2-class cross-entropy (mean over pixels).
//! * uv: L1 between the UV map and a ground-truth UV map (reported, not in the total,
//!   as in `Loss8`).
//!
//! `total = corr + shape + kl + seg + entropy`. Each returned term already
//! includes its weight. [`PerspNetLoss`] also reproduces the official schedule that
//! lowers the weights once `L_corr` falls below 0.1 and 0.01 (the change is sticky).
//!
//! [`LossVariant::Paper`] is the paper's text (Kao et al., TIP 2023, section III-A and
//! the implementation details of section V-A; equations numbered in order of
//! appearance): `L = 0.5 L_S + 0.01 L_M + 1.0 L_corr + 0.01 L_seg` (eq. 8) with
//! * `L_S` (eq. 4): the L1 between the ground-truth and predicted UV position maps,
//!   weighted 1 at the vertices' UV coordinates and 0 elsewhere. At a vertex's UV
//!   coordinate the ground-truth map holds the vertex itself (eq. 3 renders the mesh
//!   there), so this is the L1 between X read from the predicted map at the vertex UVs
//!   and `9 x` the mesh: the same term as the official `L_S`, at weight 0.5.
//! * `L_M` (eq. 6): `(1/m) (sum_i KL_i + lambda sum_i H(M_i))` with `lambda = 0.1`, the
//!   KL taken from the barycentric rows to the predicted rows (the other direction is
//!   infinite wherever the ground-truth row is zero); weighted 0.01, it is the KL
//!   summed over the points over `B x M` at 0.01 plus the mean row entropy at 0.001.
//! * `L_corr` (eq. 7): a plain L1 on `X_corr = M X` (summed over xyz, mean over points;
//!   no quadratic zone).
//! * `L_seg`: 2-class softmax cross-entropy, weight 0.01.
//!
//! The weights are fixed (no schedule). The paper writes `L_S` and `L_corr` as sums;
//! they are averaged here over the vertices and the points, as the official code does
//! (its lowered weights 0.5 / 0.01 / 0.001 are the paper's `lambda_1`, `lambda_2` and
//! `lambda_2 lambda`, so the paper's weights were set at these normalisations).

use candle_core::{D, DType, Result, Tensor};
use serde::{Deserialize, Serialize};

use crate::config::{LossVariant, PerspNetConfig};
use crate::layers;
use crate::model::{PerspNetOutput, UV_SCALE};

/// Factor between canonical units and the ground-truth coordinate map in the
/// official loss (`coords = bmm(softmax(A), X / 9 * 4.5)`).
pub const NOCS_SCALE: f64 = 4.5;

/// Ground-truth soft assignment of each chosen pixel to the vertices.
#[derive(Debug, Clone)]
pub enum CorrTarget {
    /// Dense `B x M x V` probabilities (rows sum to 1).
    Dense(Tensor),
    /// Barycentric form: `ids` `B x M x 3` (u32 vertex ids, distinct per point) and
    /// `weights` `B x M x 3` (summing to 1).
    Sparse {
        /// Vertex ids of the triangle that contains the pixel's surface point.
        ids: Tensor,
        /// Barycentric weights of those vertices.
        weights: Tensor,
    },
}

/// Ground truth for one batch.
#[derive(Debug, Clone, Copy)]
pub struct LossTargets<'a> {
    /// Ground-truth coordinates at the chosen pixels, `B x M x 3`, in the official
    /// scale (`4.5 x` canonical mesh units).
    pub nocs: &'a Tensor,
    /// Canonical mesh vertices, `B x V x 3`.
    pub model: &'a Tensor,
    /// Face mask `B x H x W` with values 0 / 1 (any numeric dtype).
    pub seg_mask: &'a Tensor,
    /// Ground-truth assignment.
    pub corr: &'a CorrTarget,
    /// Optional ground-truth UV map `B x 3 x H x W` (only reported).
    pub uv_map: Option<&'a Tensor>,
}

/// Loss weights. [`LossWeights::default`] gives the official initial values.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossWeights {
    /// Weight of `L_corr` (1.0).
    pub corr: f64,
    /// Weight of the shape L1 `L_S` (1.0).
    pub shape: f64,
    /// Weight of the KL term (0.1).
    pub kl: f64,
    /// Weight of the segmentation cross-entropy (0.1).
    pub seg: f64,
    /// Weight of the entropy term (0.001).
    pub entropy: f64,
    /// Weight of the (reported only) UV-map L1 (1.0).
    pub uv: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            corr: 1.0,
            shape: 1.0,
            kl: 0.1,
            seg: 0.1,
            entropy: 0.001,
            uv: 1.0,
        }
    }
}

impl LossWeights {
    /// The paper's fixed weights (section V-A): `lambda_1 = 0.5` on `L_S`,
    /// `lambda_2 = 0.01` on `L_M` (so 0.01 on the KL and `0.01 x lambda = 0.001` on the
    /// entropy, `lambda = 0.1`), `lambda_3 = 1.0` on `L_corr`, `lambda_4 = 0.01` on
    /// `L_seg`. The UV weight (a reported term, never in the total) stays 1.
    pub fn paper() -> Self {
        Self {
            corr: 1.0,
            shape: 0.5,
            kl: 0.01,
            seg: 0.01,
            entropy: 0.01 * 0.1,
            uv: 1.0,
        }
    }

    /// The weights of `variant` at the start of a run.
    pub fn initial(variant: LossVariant) -> Self {
        match variant {
            LossVariant::Official => Self::default(),
            LossVariant::Paper => Self::paper(),
        }
    }

    /// The official schedule, applied with the current (weighted) `L_corr`:
    /// below 0.01 the KL weight becomes 0.001 and the shape and UV weights 0.5;
    /// otherwise below 0.1 KL and segmentation become 0.01 and shape 1.0.
    pub fn update_schedule(&mut self, corr_loss: f64) {
        if corr_loss < 0.01 {
            self.kl = 0.001;
            self.uv = 0.5;
            self.shape = 0.5;
        } else if corr_loss < 0.1 {
            self.kl = 0.01;
            self.seg = 0.01;
            self.shape = 1.0;
        }
    }
}

/// The loss terms of one batch (each already weighted) and their sum.
#[derive(Debug, Clone)]
pub struct LossTerms {
    /// `corr + shape + kl + seg + entropy` (scalar).
    pub total: Tensor,
    /// Weighted `L_corr`.
    pub corr: Tensor,
    /// Weighted shape L1 `L_S`.
    pub shape: Tensor,
    /// Weighted KL divergence.
    pub kl: Tensor,
    /// Weighted entropy term.
    pub entropy: Tensor,
    /// Weighted segmentation cross-entropy.
    pub seg: Tensor,
    /// Weighted UV-map L1, when a ground-truth UV map was given (not in `total`).
    pub uv: Option<Tensor>,
}

impl LossTerms {
    /// The scalar values `(total, corr, shape, kl, entropy, seg)`.
    pub fn values(&self) -> Result<[f32; 6]> {
        let v = |t: &Tensor| t.to_dtype(DType::F32)?.to_scalar::<f32>();
        Ok([
            v(&self.total)?,
            v(&self.corr)?,
            v(&self.shape)?,
            v(&self.kl)?,
            v(&self.entropy)?,
            v(&self.seg)?,
        ])
    }
}

/// Stateful loss with the official weight schedule.
#[derive(Debug, Clone)]
pub struct PerspNetLoss {
    /// Current weights (updated by the schedule when `schedule` is true).
    pub weights: LossWeights,
    /// Smooth-L1 threshold (0.01; 0 makes `L_corr` a plain L1, as the paper's).
    pub threshold: f64,
    /// Whether to apply [`LossWeights::update_schedule`] on every call.
    pub schedule: bool,
    /// Whether `L_M` (KL and entropy) is in the loss; without it (the paper's "w/o
    /// L_M" ablation) both terms are computed at weight 0, whatever the schedule says.
    pub assignment: bool,
}

impl Default for PerspNetLoss {
    fn default() -> Self {
        Self::new(LossVariant::Official)
    }
}

impl PerspNetLoss {
    /// The loss of `variant` at its starting weights.
    pub fn new(variant: LossVariant) -> Self {
        let official = variant == LossVariant::Official;
        Self {
            weights: LossWeights::initial(variant),
            threshold: if official { 0.01 } else { 0.0 },
            schedule: official,
            assignment: true,
        }
    }

    /// The loss a network of `cfg` trains with: its variant, with or without `L_M`.
    pub(crate) fn for_config(cfg: &PerspNetConfig) -> Self {
        Self {
            assignment: cfg.assignment_loss,
            ..Self::new(cfg.loss)
        }
    }

    /// The weights the terms are computed with: [`Self::weights`], with the KL and
    /// entropy weights 0 when `L_M` is off.
    pub(crate) fn effective_weights(&self) -> LossWeights {
        let mut w = self.weights;
        if !self.assignment {
            w.kl = 0.0;
            w.entropy = 0.0;
        }
        w
    }

    /// Computes the loss terms, first updating the weights from `L_corr` when the
    /// schedule is on (as the official code does before weighting the other terms).
    pub fn compute(&mut self, out: &PerspNetOutput, t: &LossTargets) -> Result<LossTerms> {
        let corr = corr_loss(out, t.nocs, self.threshold)?.affine(self.weights.corr, 0.0)?;
        if self.schedule {
            let c = corr.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            self.weights.update_schedule(c);
        }
        perspnet_loss_with_corr(out, t, &self.effective_weights(), corr)
    }
}

/// Computes all terms with fixed `weights` (no schedule).
pub fn perspnet_loss(
    out: &PerspNetOutput,
    t: &LossTargets,
    weights: &LossWeights,
) -> Result<LossTerms> {
    let corr = corr_loss(out, t.nocs, 0.01)?.affine(weights.corr, 0.0)?;
    perspnet_loss_with_corr(out, t, weights, corr)
}

fn perspnet_loss_with_corr(
    out: &PerspNetOutput,
    t: &LossTargets,
    w: &LossWeights,
    corr: Tensor,
) -> Result<LossTerms> {
    loss_terms_with_corr(
        &out.assign_logits,
        &out.vertices,
        &out.dense.seg_logits,
        &out.dense.uv_map,
        t,
        w,
        corr,
    )
}

/// The loss terms from the network's raw outputs (assignment logits `B x M x V`,
/// vertices X `B x V x 3` in UV-map units, segmentation logits `B x 2 x H x W`, UV map
/// `B x 3 x H x W`) with fixed weights `w` and `L_corr`'s smooth-L1 `threshold` (0: the
/// paper's plain L1). [`PerspNetLoss::compute`] is this plus the official schedule (the
/// unit tests' entry).
#[cfg(test)]
fn loss_terms(
    assign_logits: &Tensor,
    vertices: &Tensor,
    seg_logits: &Tensor,
    uv_map: &Tensor,
    t: &LossTargets,
    w: &LossWeights,
    threshold: f64,
) -> Result<LossTerms> {
    let corr = corr_loss_parts(assign_logits, vertices, t.nocs, threshold)?.affine(w.corr, 0.0)?;
    loss_terms_with_corr(assign_logits, vertices, seg_logits, uv_map, t, w, corr)
}

fn loss_terms_with_corr(
    assign_logits: &Tensor,
    vertices: &Tensor,
    seg_logits: &Tensor,
    uv_map: &Tensor,
    t: &LossTargets,
    w: &LossWeights,
    corr: Tensor,
) -> Result<LossTerms> {
    let (b, m, _v) = assign_logits.dims3()?;
    let log_p = layers::log_softmax_last(assign_logits)?;

    let kl = kl_loss(&log_p, t.corr)?.affine(w.kl / (b * m) as f64, 0.0)?;
    let entropy = layers::row_entropy(&log_p)?
        .mean_all()?
        .affine(w.entropy, 0.0)?;
    let model = t.model.to_dtype(vertices.dtype())?.affine(UV_SCALE, 0.0)?;
    let shape = (vertices - model)?
        .abs()?
        .mean_all()?
        .affine(w.shape, 0.0)?;
    let seg = seg_cross_entropy(seg_logits, t.seg_mask)?.affine(w.seg, 0.0)?;
    let uv = match t.uv_map {
        Some(gt) => Some((uv_map - gt)?.abs()?.mean_all()?.affine(w.uv, 0.0)?),
        None => None,
    };
    let total = (((&corr + &shape)? + &kl)? + &seg)?.add(&entropy)?;
    Ok(LossTerms {
        total,
        corr,
        shape,
        kl,
        entropy,
        seg,
        uv,
    })
}

/// Unweighted `L_corr`: smooth L1 between `softmax(A) X / 2` and `nocs`.
pub fn corr_loss(out: &PerspNetOutput, nocs: &Tensor, threshold: f64) -> Result<Tensor> {
    corr_loss_parts(&out.assign_logits, &out.vertices, nocs, threshold)
}

/// [`corr_loss`] from the assignment logits and the vertices.
pub fn corr_loss_parts(
    assign_logits: &Tensor,
    vertices: &Tensor,
    nocs: &Tensor,
    threshold: f64,
) -> Result<Tensor> {
    let coords = layers::softmax_last(assign_logits)?
        .matmul(vertices)?
        .affine(NOCS_SCALE / UV_SCALE, 0.0)?;
    smooth_l1_sum_mean(&coords, nocs, threshold)
}

/// Smooth L1 with the official parametrisation (`d^2 / (2 th)` below `th`,
/// `d - th / 2` above), summed over the last axis and averaged over the rest.
/// `threshold = 0` is the plain L1 `d`.
pub fn smooth_l1_sum_mean(pred: &Tensor, target: &Tensor, threshold: f64) -> Result<Tensor> {
    let diff = (pred - target.to_dtype(pred.dtype())?)?.abs()?;
    if threshold <= 0.0 {
        return diff.sum(D::Minus1)?.mean_all();
    }
    // q = min(d, th): q^2 / (2 th) + (d - q) equals both branches.
    let q = diff.clamp(0.0, threshold)?;
    let l = (q.sqr()?.affine(1.0 / (2.0 * threshold), 0.0)? + (&diff - &q)?)?;
    l.sum(D::Minus1)?.mean_all()
}

/// `sum(target * (ln target - log_p))` over all entries (PyTorch `kl_div(..., size_average=False)`).
pub fn kl_loss(log_p: &Tensor, target: &CorrTarget) -> Result<Tensor> {
    match target {
        CorrTarget::Dense(tgt) => {
            let tgt = tgt.to_dtype(log_p.dtype())?;
            let tlogt = (&tgt * tgt.clamp(1e-30, f64::INFINITY)?.log()?)?.sum_all()?;
            tlogt - (tgt * log_p)?.sum_all()?
        }
        CorrTarget::Sparse { ids, weights } => {
            let wts = weights.to_dtype(log_p.dtype())?;
            let picked = log_p.gather(&ids.to_dtype(DType::U32)?.contiguous()?, D::Minus1)?;
            let tlogt = (&wts * wts.clamp(1e-30, f64::INFINITY)?.log()?)?.sum_all()?;
            tlogt - (wts * picked)?.sum_all()?
        }
    }
}

/// Mean 2-class cross-entropy of `B x 2 x H x W` logits against a `B x H x W` 0/1 mask.
pub fn seg_cross_entropy(logits: &Tensor, mask: &Tensor) -> Result<Tensor> {
    let log_p = candle_nn::ops::log_softmax(logits, 1)?;
    let m = mask.to_dtype(log_p.dtype())?;
    let lp0 = log_p.narrow(1, 0, 1)?.squeeze(1)?;
    let lp1 = log_p.narrow(1, 1, 1)?.squeeze(1)?;
    let ll = ((&m * lp1)? + (m.affine(-1.0, 1.0)? * lp0)?)?;
    ll.mean_all()?.neg()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Every term of `--loss paper` on a 1 x 2-point x 3-vertex input, each worked out
    /// by hand, and the weighted total 0.5 L_S + 0.01 L_M + 1.0 L_corr + 0.01 L_seg.
    #[test]
    fn paper_loss_terms_by_hand() -> Result<()> {
        let dev = Device::Cpu;
        let (ln2, ln3) = (2f64.ln(), 3f64.ln());
        // Rows of M: softmax([0, ln2, 0]) = [1/4, 1/2, 1/4]; softmax([ln3, 0, 0]) = [3/5, 1/5, 1/5].
        let logits = Tensor::new(&[[[0f32, ln2 as f32, 0.0], [ln3 as f32, 0.0, 0.0]]], &dev)?;
        // X in UV-map units (9 x canonical): 9 times the identity.
        let vertices = Tensor::new(&[[[9f32, 0., 0.], [0., 9., 0.], [0., 0., 9.]]], &dev)?;
        // M X / 9 * 4.5 = 4.5 M: [1.125, 2.25, 1.125] and [2.7, 0.9, 0.9].
        let nocs = Tensor::new(&[[[1f32, 2., 1.], [3., 1., 1.]]], &dev)?;
        // L1 per point: 0.125 + 0.25 + 0.125 = 0.5 and 0.3 + 0.1 + 0.1 = 0.5; mean 0.5.
        let l_corr = 0.5;
        // 9 x mesh differs from X by 4.5 in one of 9 coordinates: mean L1 0.5.
        let model = Tensor::new(&[[[1f32, 0., 0.], [0., 1., 0.], [0., 0., 0.5]]], &dev)?;
        let l_s = 0.5;
        // Barycentric rows: the first equals M's row (KL 0), the second is all on
        // vertex 0 (KL ln(1 / (3/5)) = ln(5/3)).
        let ids = Tensor::new(&[[[0u32, 1, 2], [0, 1, 2]]], &dev)?;
        let weights = Tensor::new(&[[[0.25f32, 0.5, 0.25], [1., 0., 0.]]], &dev)?;
        let corr_t = CorrTarget::Sparse { ids, weights };
        let kl_mean = (5f64 / 3.0).ln() / 2.0;
        let h0 = 1.5 * ln2;
        let h1 = -(0.6 * 0.6f64.ln() + 0.4 * 0.2f64.ln());
        let l_m = kl_mean + 0.1 * (h0 + h1) / 2.0;
        // Segmentation: class-1 logits ln3, ln3, 0, 0 against class-0 zeros; mask 1 0 1 1.
        let seg_logits = Tensor::new(
            &[[[[0f32, 0.], [0., 0.]], [[ln3 as f32, ln3 as f32], [0., 0.]]]],
            &dev,
        )?;
        let mask = Tensor::new(&[[[1f32, 0.], [1., 1.]]], &dev)?;
        // -ln(3/4), -ln(1/4), -ln(1/2), -ln(1/2): mean.
        let l_seg = ((4f64 / 3.0).ln() + 4f64.ln() + 2.0 * ln2) / 4.0;
        let uv_map = Tensor::zeros((1, 3, 2, 2), DType::F32, &dev)?;
        let t = LossTargets {
            nocs: &nocs,
            model: &model,
            seg_mask: &mask,
            corr: &corr_t,
            uv_map: None,
        };
        let loss = PerspNetLoss::new(LossVariant::Paper);
        assert_eq!((loss.threshold, loss.schedule), (0.0, false));
        let terms = loss_terms(
            &logits,
            &vertices,
            &seg_logits,
            &uv_map,
            &t,
            &loss.weights,
            loss.threshold,
        )?;
        let [total, corr, shape, kl, entropy, seg] = terms.values()?.map(f64::from);
        let close = |a: f64, b: f64, what: &str| {
            assert!(
                (a - b).abs() < 1e-6 * b.abs().max(1.0),
                "{what}: {a} vs {b}"
            )
        };
        close(corr, l_corr, "L_corr");
        close(shape, 0.5 * l_s, "0.5 L_S");
        close(kl + entropy, 0.01 * l_m, "0.01 L_M");
        close(entropy, 0.01 * 0.1 * (h0 + h1) / 2.0, "entropy");
        close(seg, 0.01 * l_seg, "0.01 L_seg");
        close(
            total,
            0.5 * l_s + 0.01 * l_m + l_corr + 0.01 * l_seg,
            "total",
        );
        // Without L_M (the "w/o L_M" ablation): the KL and entropy are 0 and the total
        // is the other three terms.
        let mut cfg = PerspNetConfig::tiny();
        cfg.loss = LossVariant::Paper;
        cfg.assignment_loss = false;
        let off = PerspNetLoss::for_config(&cfg);
        let terms = loss_terms(
            &logits,
            &vertices,
            &seg_logits,
            &uv_map,
            &t,
            &off.effective_weights(),
            off.threshold,
        )?;
        let [total, corr, _, kl, entropy, _] = terms.values()?.map(f64::from);
        assert_eq!((kl, entropy), (0.0, 0.0));
        close(corr, l_corr, "L_corr without L_M");
        close(
            total,
            0.5 * l_s + l_corr + 0.01 * l_seg,
            "total without L_M",
        );
        Ok(())
    }
}
