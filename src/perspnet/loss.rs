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
//! [`LossVariant::Paper`] is the paper's description instead, where it departs from
//! the code in a way that has one clear reading: `L_corr` a plain L1 on `X_corr`
//! (summed over xyz, mean over points; no quadratic zone below 0.01) and the weights
//! held at their starting values (no schedule). The other terms are the same in both.

use candle_core::{D, DType, Result, Tensor};
use serde::{Deserialize, Serialize};

use super::config::LossVariant;
use super::model::{PerspNetOutput, UV_SCALE};

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
            weights: LossWeights::default(),
            threshold: if official { 0.01 } else { 0.0 },
            schedule: official,
        }
    }

    /// Computes the loss terms, first updating the weights from `L_corr` when the
    /// schedule is on (as the official code does before weighting the other terms).
    pub fn compute(&mut self, out: &PerspNetOutput, t: &LossTargets) -> Result<LossTerms> {
        let corr = corr_loss(out, t.nocs, self.threshold)?.affine(self.weights.corr, 0.0)?;
        if self.schedule {
            let c = corr.to_dtype(DType::F64)?.to_scalar::<f64>()?;
            self.weights.update_schedule(c);
        }
        perspnet_loss_with_corr(out, t, &self.weights, corr)
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
    let (b, m, _v) = out.assign_logits.dims3()?;
    let log_p = super::layers::log_softmax_last(&out.assign_logits)?;

    let kl = kl_loss(&log_p, t.corr)?.affine(w.kl / (b * m) as f64, 0.0)?;
    let entropy = super::layers::row_entropy(&log_p)?
        .mean_all()?
        .affine(w.entropy, 0.0)?;
    let model = t
        .model
        .to_dtype(out.vertices.dtype())?
        .affine(UV_SCALE, 0.0)?;
    let shape = (&out.vertices - model)?
        .abs()?
        .mean_all()?
        .affine(w.shape, 0.0)?;
    let seg = seg_cross_entropy(&out.dense.seg_logits, t.seg_mask)?.affine(w.seg, 0.0)?;
    let uv = match t.uv_map {
        Some(gt) => Some(
            (&out.dense.uv_map - gt)?
                .abs()?
                .mean_all()?
                .affine(w.uv, 0.0)?,
        ),
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
    let coords = out.correspondences()?.affine(NOCS_SCALE / UV_SCALE, 0.0)?;
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
