//! placeholder
#![allow(missing_docs, dead_code)]
use crate::error::Result;
use std::path::Path;
pub struct NpyArray;
impl NpyArray {
    pub fn shape(&self) -> &[usize] { &[] }
    pub fn to_i64_vec(&self) -> Result<Vec<i64>> { unimplemented!() }
    pub fn to_f32_vec(&self) -> Vec<f32> { unimplemented!() }
}
pub fn read_npy(_p: &Path) -> Result<NpyArray> { unimplemented!() }
