//! Writers of synthetic input shared by several test files.

pub mod biwi_writer;
