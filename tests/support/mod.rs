//! Writers of synthetic input shared by several test files (each test file uses some).

#![allow(dead_code)]

pub mod biwi_writer;
pub mod converted;
pub mod png_bomb;
