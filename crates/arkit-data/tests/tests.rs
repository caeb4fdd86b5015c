//! `arkit-data`'s integration tests, one binary, each module a stage's behaviour through
//! the library's own paths (the commands' end-to-end tests are the workspace root's).

mod support;

mod augment;
mod crop_store;
mod eval;
mod loader;
mod real_topology;
mod schemas;
