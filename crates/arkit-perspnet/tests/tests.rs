//! The integration tests of `arkit-perspnet`, one binary: the network, its layers,
//! losses and training ([`perspnet`]), the faces of a photo in one batch ([`photo`]) and
//! the direct baseline ([`direct`]). The
//! commands that use the crate (`train`, `predict --model`, the weights commands, the
//! demo) are tested at the workspace's root.

mod support;

mod direct;
mod perspnet;
mod photo;
