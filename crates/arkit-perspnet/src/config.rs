//! Serde-serialisable hyper-parameters of [`crate::PerspNet`].

use serde::{Deserialize, Serialize};

/// Hyper-parameters of PerspNet. [`PerspNetConfig::paper`] reproduces the
/// official shapes; [`PerspNetConfig::tiny`] is a scaled-down variant that
/// trains in minutes on a CPU.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerspNetConfig {
    /// Side of the square input crop in pixels (must be a multiple of 32).
    pub input_size: usize,
    /// Widths of the four ResNet-18 stages (the stem has `encoder_widths[0]` channels).
    pub encoder_widths: [usize; 4],
    /// Channels of the 3x3 conv + BN + ReLU after the encoder (`fcdim`).
    pub fc_channels: usize,
    /// Widths of the four decoder stages at strides 16, 8, 4, 2.
    pub decoder_widths: [usize; 4],
    /// Channels of the full-resolution image and UV feature maps (`raw_dim`).
    pub feature_channels: usize,
    /// Output channels of the 1x1 conv applied to the sampled image features.
    pub color_channels: usize,
    /// Channels of the 2D sine/cosine position encoding (multiple of 4).
    pub pos_channels: usize,
    /// Hidden width of the two global-feature MLPs (128 in the paper).
    pub global_hidden: usize,
    /// Width of the 2D and 3D global features (1024 in the paper).
    pub global_channels: usize,
    /// Hidden widths of the assignment MLP (512, 256 in the paper).
    pub assign_hidden: [usize; 2],
    /// Number of sampled pixels per image (`n_pts`, M).
    pub points: usize,
    /// Number of mesh vertices (1,220 for the ARKit face mesh).
    pub vertices: usize,
    /// Channel-wise (Dropout2d) probability used in training.
    pub dropout: f64,
    /// Standard deviation of the normal weight initialisation.
    pub init_std: f64,
    /// Batch-norm epsilon.
    pub bn_eps: f64,
    /// Batch-norm running-statistics momentum (PyTorch convention).
    pub bn_momentum: f64,
    /// Which reading of the loss to train with (older configs: the official code's).
    #[serde(default)]
    pub loss: LossVariant,
    /// Whether the points' local features carry the 2D position encoding (the paper's
    /// ablation "w/o PE" turns it off: the local feature is the image feature alone).
    #[serde(default = "yes")]
    pub position_encoding: bool,
    /// Whether the loss has the assignment term `L_M` (KL and entropy; the paper's
    /// ablation "w/o L_M" turns it off, leaving M supervised through `L_corr` only).
    #[serde(default = "yes")]
    pub assignment_loss: bool,
    /// Which network: PerspNet (the default; older configs) or the paper's "Direct
    /// 6DoF Regress" baseline (`crate::direct`), which uses the encoder's
    /// settings (`input_size`, `encoder_widths`, `fc_channels` as its head's width,
    /// `init_std`, `bn_eps`, `bn_momentum`) and ignores the rest.
    #[serde(default)]
    pub architecture: Architecture,
}

/// The network a config builds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Architecture {
    /// PerspNet: dense correspondences, then PnP.
    #[default]
    PerspNet,
    /// The paper's "Direct 6DoF Regress": the ResNet-18 encoder and a head regressing
    /// the rotation (6D) and the translation (in the crop's frame).
    Direct,
}

impl std::str::FromStr for Architecture {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "perspnet" => Ok(Self::PerspNet),
            "direct" => Ok(Self::Direct),
            other => Err(format!(
                "unknown architecture '{other}': perspnet or direct"
            )),
        }
    }
}

fn yes() -> bool {
    true
}

/// The two readings of PerspNet's loss: the official code's (the default) and the
/// paper's text. Both have the same five terms (correspondence, shape, KL with entropy,
/// segmentation); see `crate::loss` for each.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LossVariant {
    /// `models/loss.py`: smooth L1 (threshold 0.01) on the correspondences, and the
    /// weights lowered as `L_corr` falls below 0.1 and 0.01.
    #[default]
    Official,
    /// The paper's text: a plain L1 on the correspondences and fixed weights.
    Paper,
}

impl std::str::FromStr for LossVariant {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "official" => Ok(Self::Official),
            "paper" => Ok(Self::Paper),
            other => Err(format!("unknown loss '{other}': official or paper")),
        }
    }
}

impl PerspNetConfig {
    /// The official configuration: 192x192 input, ResNet-18 widths
    /// 64/128/256/512, decoder 256/128/64/32, 32 feature channels, M = 1024,
    /// 1,220 vertices.
    pub fn paper() -> Self {
        Self {
            input_size: 192,
            encoder_widths: [64, 128, 256, 512],
            fc_channels: 256,
            decoder_widths: [256, 128, 64, 32],
            feature_channels: 32,
            color_channels: 64,
            pos_channels: 64,
            global_hidden: 128,
            global_channels: 1024,
            assign_hidden: [512, 256],
            points: 1024,
            vertices: 1220,
            dropout: 0.15,
            init_std: 0.02,
            bn_eps: 1e-5,
            bn_momentum: 0.1,
            loss: LossVariant::Official,
            position_encoding: true,
            assignment_loss: true,
            architecture: Architecture::PerspNet,
        }
    }

    /// A small configuration for tests and quick CPU experiments:
    /// 64x64 input, widths 16/32/64/128, decoder 64/32/16/16, 16 feature
    /// channels, M = 256, heads scaled down by 4-8x.
    pub fn tiny() -> Self {
        Self {
            input_size: 64,
            encoder_widths: [16, 32, 64, 128],
            fc_channels: 64,
            decoder_widths: [64, 32, 16, 16],
            feature_channels: 16,
            color_channels: 16,
            pos_channels: 16,
            global_hidden: 32,
            global_channels: 128,
            assign_hidden: [128, 64],
            points: 256,
            vertices: 1220,
            dropout: 0.15,
            init_std: 0.02,
            bn_eps: 1e-5,
            bn_momentum: 0.1,
            loss: LossVariant::Official,
            position_encoding: true,
            assignment_loss: true,
            architecture: Architecture::PerspNet,
        }
    }

    /// Channels of the per-point local feature (`color_channels + pos_channels`, 128 in
    /// the paper; `color_channels` without the position encoding).
    pub fn local_channels(&self) -> usize {
        self.color_channels
            + if self.position_encoding {
                self.pos_channels
            } else {
                0
            }
    }

    /// Input channels of the assignment MLP (local + 2D global + 3D global, 2176 in the paper).
    pub fn assign_in_channels(&self) -> usize {
        self.local_channels() + 2 * self.global_channels
    }

    /// Checks the constraints the model relies on.
    pub fn validate(&self) -> Result<(), String> {
        if self.input_size == 0 || !self.input_size.is_multiple_of(32) {
            return Err(format!(
                "input_size {} must be a positive multiple of 32",
                self.input_size
            ));
        }
        if self.pos_channels == 0 || !self.pos_channels.is_multiple_of(4) {
            return Err(format!(
                "pos_channels {} must be a positive multiple of 4",
                self.pos_channels
            ));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(format!("dropout {} must be in [0, 1)", self.dropout));
        }
        if self.points == 0 || self.vertices == 0 {
            return Err("points and vertices must be positive".into());
        }
        // Bounds a real network stays within; beyond them a config file would ask for
        // more memory than any machine has (or zero-width layers) before anything runs.
        if self.input_size > 1024 {
            return Err(format!(
                "input_size {} must be at most 1024",
                self.input_size
            ));
        }
        let widths = [
            ("encoder_widths", &self.encoder_widths[..]),
            ("decoder_widths", &self.decoder_widths[..]),
            ("assign_hidden", &self.assign_hidden[..]),
            ("fc_channels", &[self.fc_channels][..]),
            ("feature_channels", &[self.feature_channels][..]),
            ("color_channels", &[self.color_channels][..]),
            ("pos_channels", &[self.pos_channels][..]),
            ("global_hidden", &[self.global_hidden][..]),
            ("global_channels", &[self.global_channels][..]),
        ];
        for (name, w) in widths {
            if w.iter().any(|&c| !(1..=8192).contains(&c)) {
                return Err(format!("{name} {w:?}: every width must be in 1..=8192"));
            }
        }
        if self.points > 65_536 {
            return Err(format!("points {} must be at most 65536", self.points));
        }
        if self.vertices > 1_000_000 {
            return Err(format!(
                "vertices {} must be at most 1000000",
                self.vertices
            ));
        }
        if !(self.init_std.is_finite() && self.init_std > 0.0 && self.init_std <= 1.0) {
            return Err(format!("init_std {} must be in (0, 1]", self.init_std));
        }
        if !(self.bn_eps.is_finite() && self.bn_eps > 0.0 && self.bn_eps <= 1.0) {
            return Err(format!("bn_eps {} must be in (0, 1]", self.bn_eps));
        }
        if !(0.0..=1.0).contains(&self.bn_momentum) {
            return Err(format!(
                "bn_momentum {} must be in [0, 1]",
                self.bn_momentum
            ));
        }
        Ok(())
    }
}

impl Default for PerspNetConfig {
    fn default() -> Self {
        Self::paper()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_names_the_field_out_of_range() {
        type Break = fn(&mut PerspNetConfig);
        let cases: [(&str, Break); 9] = [
            ("input_size", |c| c.input_size = 2048),
            ("input_size", |c| c.input_size = 0),
            ("encoder_widths", |c| c.encoder_widths[2] = 0),
            ("global_channels", |c| c.global_channels = 1 << 20),
            ("points", |c| c.points = 100_000),
            ("init_std", |c| c.init_std = f64::NAN),
            ("bn_eps", |c| c.bn_eps = -1.0),
            ("bn_momentum", |c| c.bn_momentum = 2.0),
            ("dropout", |c| c.dropout = 1.0),
        ];
        for (field, break_it) in cases {
            let mut c = PerspNetConfig::tiny();
            break_it(&mut c);
            let e = c.validate().unwrap_err();
            assert!(e.starts_with(field), "{field}: {e}");
        }
    }

    /// Older configs are PerspNet's; `"direct"` and the flag's spelling select the
    /// baseline; anything else is refused by name.
    #[test]
    fn architecture_from_json_and_flag() {
        let mut v = serde_json::to_value(PerspNetConfig::tiny()).unwrap();
        assert_eq!(v["architecture"], "perspnet");
        v.as_object_mut().unwrap().remove("architecture");
        let old: PerspNetConfig = serde_json::from_value(v.clone()).unwrap();
        assert_eq!(old.architecture, Architecture::PerspNet);
        v["architecture"] = "direct".into();
        let direct: PerspNetConfig = serde_json::from_value(v.clone()).unwrap();
        assert_eq!(direct.architecture, Architecture::Direct);
        v["architecture"] = "resnet".into();
        assert!(serde_json::from_value::<PerspNetConfig>(v).is_err());
        assert_eq!("direct".parse::<Architecture>(), Ok(Architecture::Direct));
        assert!(
            "Direct"
                .parse::<Architecture>()
                .unwrap_err()
                .contains("perspnet or direct")
        );
    }

    #[test]
    fn json_round_trip() {
        for c in [PerspNetConfig::paper(), PerspNetConfig::tiny()] {
            c.validate().unwrap();
            let s = serde_json::to_string(&c).unwrap();
            let back: PerspNetConfig = serde_json::from_str(&s).unwrap();
            assert_eq!(back, c);
        }
        assert_eq!(PerspNetConfig::paper().assign_in_channels(), 2176);
    }

    /// A config file from before the `loss` field reads as the official loss; `"paper"`
    /// and the `--loss` spelling select the paper's; anything else is refused by name.
    #[test]
    fn loss_variant_from_json_and_flag() {
        let mut v = serde_json::to_value(PerspNetConfig::tiny()).unwrap();
        v.as_object_mut().unwrap().remove("loss");
        let old: PerspNetConfig = serde_json::from_value(v.clone()).unwrap();
        assert_eq!(old.loss, LossVariant::Official);
        v["loss"] = "paper".into();
        let paper: PerspNetConfig = serde_json::from_value(v.clone()).unwrap();
        assert_eq!(paper.loss, LossVariant::Paper);
        v["loss"] = "smooth".into();
        assert!(serde_json::from_value::<PerspNetConfig>(v).is_err());
        assert_eq!("paper".parse::<LossVariant>(), Ok(LossVariant::Paper));
        assert!(
            "Paper"
                .parse::<LossVariant>()
                .unwrap_err()
                .contains("official or paper")
        );
    }
}
