//! `mesh`: the face's topology, the facts every geometric stage shares.
//!
//! Contract: a [`topology::FaceTopology`] is checked when it is built (triangles index
//! existing vertices, one UV per vertex, landmarks in range) and is immutable after; the
//! derived facts (boundary loops, hole fills, the mirror map) are computed from it once.
//! [`synthetic_face`] is the built-in stand-in face (not Apple's mesh) that lets every
//! command run without the release. Depends on `arkit_core` only.

pub mod synthetic_face;
pub mod topology;
