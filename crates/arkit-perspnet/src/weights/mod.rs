//! Weights in and out of the network: PyTorch `state_dict`s ([`state_dict`]) and
//! safetensors files read without trusting them ([`safetensors_file`]).

pub mod safetensors_file;
pub mod state_dict;

pub use state_dict::*;
