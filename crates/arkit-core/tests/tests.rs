//! `arkit-core`'s integration tests, one binary (`bounded_memory` is a second: it
//! installs a counting global allocator of its own).

mod support;

mod conventions_scipy;
mod fuzz_corpus;
mod npy_numpy_fixtures;
