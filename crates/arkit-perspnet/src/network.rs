//! The network of a config, PerspNet or the direct baseline, and the vertex UV table
//! PerspNet reads its UV map at.

use crate::candle_error::candle_err;
use crate::config::{Architecture, PerspNetConfig};
use crate::direct::DirectNet;
use crate::model::PerspNet;
use arkit_core::{Error, Result};
use arkit_data::mesh::FaceTopology;
use candle_core::{Device, Tensor};
use candle_nn::VarBuilder;

/// The `V x 2` vertex UV table the network reads its UV map at.
pub fn vertex_uv(topology: &FaceTopology, device: &Device) -> Result<Tensor> {
    let v = topology.vertex_count;
    let flat: Vec<f32> = topology.uv[..v].iter().flat_map(|t| [t[0], t[1]]).collect();
    Tensor::from_vec(flat, (v, 2), device).map_err(|e| candle_err("vertex UVs", e))
}

/// The network of a config: PerspNet or the direct baseline (its `architecture`).
#[derive(Debug, Clone)]
pub enum Network {
    /// PerspNet (correspondences, then PnP).
    PerspNet(Box<PerspNet>),
    /// The paper's "Direct 6DoF Regress" baseline.
    Direct(Box<DirectNet>),
}

impl Network {
    /// Builds the network of `cfg` with fresh variables in `vb` (`vertex_uv`: see
    /// [`PerspNet::new`]; the direct baseline does not use it).
    pub fn new(
        cfg: &PerspNetConfig,
        vertex_uv: &Tensor,
        vb: VarBuilder,
    ) -> candle_core::Result<Self> {
        Ok(match cfg.architecture {
            Architecture::PerspNet => {
                Network::PerspNet(Box::new(PerspNet::new(cfg, vertex_uv, vb)?))
            }
            Architecture::Direct => Network::Direct(Box::new(DirectNet::new(cfg, vb)?)),
        })
    }

    /// The PerspNet, or an error naming what needs one.
    pub fn perspnet(&self, what: &str) -> Result<&PerspNet> {
        match self {
            Network::PerspNet(n) => Ok(n),
            Network::Direct(_) => Err(Error::invalid(
                what,
                "needs a PerspNet; this model is the direct baseline (no correspondences, mask or mesh)",
            )),
        }
    }
}
