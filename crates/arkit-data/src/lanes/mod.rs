//! `lanes`: the data crate's SIMD kernels, one module per family, each beside its scalar
//! definition and behind a safe (or, where raw pointers are the contract, a documented
//! `unsafe`) function that dispatches on [`arkit_core::lanes::level`], the one place
//! that decides which CPU features the workspace uses (capped by `ARKIT_SIMD`). The
//! domain code calls only those functions. Each family's tests compare every level the
//! CPU has with its definition, calling the per-level function directly.

#[cfg(test)]
pub(crate) use arkit_core::lanes::available;
pub(crate) use arkit_core::lanes::{Level, avx512_vbmi, level};

pub(crate) mod crop;
pub(crate) mod jitter;
pub(crate) mod matrix;
pub(crate) mod normalise;
pub(crate) mod predictor;
#[cfg(target_arch = "x86_64")]
pub(crate) mod rgb;
#[cfg(target_arch = "x86_64")]
pub(crate) mod streamed_plane;
pub(crate) mod texels;
pub(crate) mod uv;
pub(crate) mod warp;
