//! `mesh`: the face's topology, the facts every geometric stage shares.
//!
//! Takes triangles, UVs and landmark indices (the release's, BIWI's or an OBJ). Gives a
//! [`FaceTopology`] and its derived facts ([`BoundaryLoops`], [`HoleFill`], the mirror
//! map), a predicted face's mesh as OBJ, PLY and landmark files ([`FaceMesh`]), and the built-in stand-in face ([`builtin`], a [`SyntheticFace`], not Apple's
//! mesh) that lets every command run without the release. Guarantees: a topology is
//! checked when it is built (triangles index existing vertices, one UV per vertex,
//! landmarks in range) and is immutable after; the derived facts are computed from it
//! once. Depends on `arkit_core` only.

pub(crate) mod face_mesh;
pub(crate) mod synthetic_face;
pub(crate) mod topology;

pub use self::{
    face_mesh::{FACE_MESH_FRAME, FaceMesh},
    synthetic_face::{FaceShapeModel, SyntheticFace, builtin},
    topology::{
        BoundaryLoops, FaceTopology, HoleFill, LANDMARK_MIRROR, LoopRole, NOSE_TIP_LANDMARK,
        nearest_mirror_partners,
    },
};
