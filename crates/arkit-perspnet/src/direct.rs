//! The paper's "Direct 6DoF Regress" baseline (its Table 2): PerspNet's ResNet-18
//! encoder, the global average of its last stage, and a two-layer head (`Linear`,
//! ReLU, `Linear`) that regresses nine numbers per crop: a rotation in the 6D
//! representation and a translation in the crop's frame. No correspondences, no PnP.
//!
//! Rotation: the 6D continuous representation of Zhou et al. (CVPR 2019): the head
//! gives the first two columns of `R` (the face-to-camera rotation in OpenCV's camera
//! frame: x right, y down, z forward), Gram-Schmidt makes them orthonormal and their
//! cross product is the third ([`rotation_from_6d`]), so every output is a rotation
//! (determinant +1) and nearby rotations have nearby outputs. Euler angles have gimbal
//! lock and wrap around, and a quaternion's `q` and `-q` are the same rotation, so
//! neither is a continuous target for a network to regress.
//!
//! Translation: not metres, which a crop cannot show (cropping removes where the face
//! was in the image and how large), but what the crop shows: `(ox, oy)`, where the
//! face's origin projects in the crop box (0 at its centre, -0.5 and 0.5 at its
//! edges), and `oz = z * side / (fx * 0.2 m)`, the width of the box at the face's
//! depth in units of 0.2 m (about a face: near 1 whatever the distance, since the box
//! is cut around the face). The crop transform and the camera's intrinsics map them
//! back to metres ([`pose_from_output`]); [`direct_target`] is the inverse, and a
//! crop shifted by `d` pixels (training's crop jitter) moves `(ox, oy)` by `d / S`.
//!
//! The head regresses the difference from a face looking at the camera at the box's
//! centre with `oz = 1` ([`OUTPUT_OFFSET`]), so a fresh network starts at that pose.
//!
//! Loss ([`direct_loss`]): the mean L1 over the nine entries of `R` against the true
//! rotation's, plus the mean L1 over `(ox, oy, oz)`, weighted equally (an entry of `R`
//! off by 0.1 is about 6 degrees; `ox` off by 0.1 is a tenth of the box).
//!
//! The rotation is the camera-frame (egocentric) one: a face off the image's centre
//! looks a little turned in its crop; in the release's images faces are near the
//! centre and the crop sees that small turn as part of the rotation to learn.
//!
//! Tests (`tests/perspnet.rs`): shapes, a rotation for any output (orthonormal,
//! determinant +1), the targets' round trip through [`pose_from_output`], the tensor
//! and the scalar Gram-Schmidt agree, a short overfit run whose loss falls, and a
//! model folder trained, saved, loaded and scored through `predict` and `eval`.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Linear, VarBuilder};
use nalgebra::{Matrix3, Vector3};

use crate::config::PerspNetConfig;
use crate::layers::{linear, relu};
use crate::model::ResNetTrunk;
use arkit_core::conventions::Pose;
use arkit_data::crop::CropTransform;
use arkit_data::pose::Intrinsics;

/// The depth unit of `oz`: the box's width at the face's depth, in units of this
/// many metres.
pub(crate) const DEPTH_UNIT_M: f64 = 0.2;

/// Added to the head's output: the 6D of `R = diag(1, -1, -1)` (the face looking at
/// the camera, in OpenCV's frame), and `(ox, oy, oz) = (0, 0, 1)`.
pub const OUTPUT_OFFSET: [f32; 9] = [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0];

/// Numbers per crop the head regresses (6D rotation, 3 translation).
pub const OUTPUTS: usize = 9;

/// The direct baseline (see the module docs).
#[derive(Debug, Clone)]
pub struct DirectNet {
    cfg: PerspNetConfig,
    trunk: ResNetTrunk,
    head: [Linear; 2],
}

impl DirectNet {
    /// Builds the network with fresh variables in `vb`: the encoder under PerspNet's
    /// names (`cnn.resnet18_8s.*`), the head as `direct_head.0` (`encoder_widths[3]`
    /// to `fc_channels`) and `direct_head.2` (`fc_channels` to 9).
    pub fn new(cfg: &PerspNetConfig, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::msg)?;
        let trunk = ResNetTrunk::new(vb.pp("cnn").pp("resnet18_8s"), cfg)?;
        let s = cfg.init_std;
        let head = [
            linear(
                vb.pp("direct_head.0"),
                cfg.encoder_widths[3],
                cfg.fc_channels,
                s,
            )?,
            linear(vb.pp("direct_head.2"), cfg.fc_channels, OUTPUTS, s)?,
        ];
        Ok(Self {
            cfg: cfg.clone(),
            trunk,
            head,
        })
    }

    /// The configuration this network was built with.
    pub fn config(&self) -> &PerspNetConfig {
        &self.cfg
    }

    /// `B x 9` for a normalised `B x 3 x H x W` crop: the 6D rotation (two columns of
    /// `R`, not yet orthonormal) and `(ox, oy, oz)`, [`OUTPUT_OFFSET`] included.
    pub fn forward(&self, img: &Tensor, train: bool) -> Result<Tensor> {
        let (_, [_, _, _, x32s]) = self.trunk.forward(img, train)?;
        let pooled = x32s.mean((2, 3))?; // B x C
        let h = relu(&self.head[0].forward(&pooled)?)?;
        let out = self.head[1].forward(&h)?;
        let offset = Tensor::from_slice(&OUTPUT_OFFSET, (1, OUTPUTS), img.device())?
            .to_dtype(out.dtype())?;
        out.broadcast_add(&offset)
    }
}

/// Gram-Schmidt of `B x 6` (two 3-vectors `a1`, `a2`) into `B x 3 x 3` rotations,
/// row-major (`[b, i, j] = R_ij`): columns `b1 = a1 / |a1|`, `b2` = `a2` less its
/// `b1` part, normalised, and `b3 = b1 x b2`.
pub fn rotation_from_6d(x: &Tensor) -> Result<Tensor> {
    let normalise = |v: &Tensor| -> Result<Tensor> {
        v.broadcast_div(&(v.sqr()?.sum_keepdim(1)? + 1e-12)?.sqrt()?)
    };
    let b1 = normalise(&x.narrow(1, 0, 3)?)?;
    let a2 = x.narrow(1, 3, 3)?;
    let along = (&b1 * &a2)?.sum_keepdim(1)?;
    let b2 = normalise(&(a2 - b1.broadcast_mul(&along)?)?)?;
    let c = |t: &Tensor, i: usize| t.narrow(1, i, 1);
    let (x1, y1, z1) = (c(&b1, 0)?, c(&b1, 1)?, c(&b1, 2)?);
    let (x2, y2, z2) = (c(&b2, 0)?, c(&b2, 1)?, c(&b2, 2)?);
    let b3 = Tensor::cat(
        &[
            ((&y1 * &z2)? - (&z1 * &y2)?)?,
            ((&z1 * &x2)? - (&x1 * &z2)?)?,
            ((&x1 * &y2)? - (&y1 * &x2)?)?,
        ],
        1,
    )?;
    Tensor::stack(&[&b1, &b2, &b3], 2)
}

/// The loss of the network's `B x 9` output against `B x 12` targets ([`direct_target`]:
/// `R` row-major, then `(ox, oy, oz)`): `(total, rotation, translation)`, where
/// rotation is the mean L1 over `R`'s entries and translation the mean L1 over
/// `(ox, oy, oz)`; total is their sum.
pub fn direct_loss(out: &Tensor, target: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
    let b = out.dim(0)?;
    let r = rotation_from_6d(&out.narrow(1, 0, 6)?)?.reshape((b, 9))?;
    let rotation = (r - target.narrow(1, 0, 9)?)?.abs()?.mean_all()?;
    let translation = (out.narrow(1, 6, 3)? - target.narrow(1, 9, 3)?)?
        .abs()?
        .mean_all()?;
    let total = (&rotation + &translation)?;
    Ok((total, rotation, translation))
}

/// [`rotation_from_6d`] for one output, in f64: always a rotation.
pub fn rotation_from_6d_f64(a: &[f64; 6]) -> Matrix3<f64> {
    // A zero (or parallel) column has no direction: the nearest axis stands in.
    let unit = |v: Vector3<f64>, fallback: Vector3<f64>| {
        let n = v.norm();
        if n > 1e-12 { v / n } else { fallback }
    };
    let b1 = unit(Vector3::new(a[0], a[1], a[2]), Vector3::x());
    let a2 = Vector3::new(a[3], a[4], a[5]);
    let other = if b1.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let b2 = unit(
        a2 - b1 * b1.dot(&a2),
        unit(other - b1 * b1.dot(&other), other),
    );
    Matrix3::from_columns(&[b1, b2, b1.cross(&b2)])
}

/// The training target of `pose` seen in `crop` of an image with intrinsics `k`, the
/// crop shifted by `shift` pixels (the view's crop jitter): `R` (OpenCV frame,
/// row-major) and `(ox, oy, oz)` (see the module docs).
pub fn direct_target(
    pose: &Pose,
    crop: &CropTransform,
    k: &Intrinsics,
    shift: (i64, i64),
) -> [f32; 12] {
    let (r, t) = pose.to_opencv();
    let (u, v) = (k.fx * t.x / t.z + k.cx, k.fy * t.y / t.z + k.cy);
    let s = crop.size as f64;
    let ox = (u - crop.x0) / crop.side - 0.5 + shift.0 as f64 / s;
    let oy = (v - crop.y0) / crop.side_y - 0.5 + shift.1 as f64 / s;
    let oz = t.z * crop.side / (k.fx * DEPTH_UNIT_M);
    let m = r.matrix();
    let mut out = [0f32; 12];
    for i in 0..3 {
        for j in 0..3 {
            out[3 * i + j] = m[(i, j)] as f32;
        }
    }
    out[9] = ox as f32;
    out[10] = oy as f32;
    out[11] = oz as f32;
    out
}

/// The pose of one `9`-number output ([`DirectNet::forward`]) for a crop `crop` of an
/// image with intrinsics `k`: the rotation from its 6D, the translation from
/// `(ox, oy, oz)` through the crop box and `k`. `None` when `oz` is not positive (the
/// face would be behind the camera) or a value is not finite.
pub fn pose_from_output(out: &[f32], crop: &CropTransform, k: &Intrinsics) -> Option<Pose> {
    if out.len() != OUTPUTS || out.iter().any(|v| !v.is_finite()) || out[8] <= 0.0 {
        return None;
    }
    let a: [f64; 6] = std::array::from_fn(|i| out[i] as f64);
    let r = rotation_from_6d_f64(&a);
    let (ox, oy, oz) = (out[6] as f64, out[7] as f64, out[8] as f64);
    let z = oz * DEPTH_UNIT_M * k.fx / crop.side;
    let u = crop.x0 + (ox + 0.5) * crop.side;
    let v = crop.y0 + (oy + 0.5) * crop.side_y;
    let t = Vector3::new((u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z);
    Some(Pose::from_opencv(
        &nalgebra::Rotation3::from_matrix_unchecked(r),
        &t,
    ))
}
