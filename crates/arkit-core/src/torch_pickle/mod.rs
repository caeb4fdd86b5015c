//! A bounded reader of what `torch.save(module.state_dict(), path)` writes, and of
//! nothing else: no code from the file is ever run, and every size it declares is
//! checked before anything is allocated from it (see [`limits`]).
//!
//! The format (PyTorch's serialization notes, "torch.save" zip format, PyTorch 1.6 and
//! later) is a zip archive whose members share one folder name (`archive/`, or the
//! file's stem for older versions): `data.pkl`, a pickle (protocol 2) of the
//! `OrderedDict` of tensors; `data/KEY`, the raw bytes of each storage; `byteorder`
//! (`little`); `version`. In the pickle, each tensor is
//! `torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad,
//! backward_hooks[, metadata])`, its storage a persistent id
//! `('storage', torch.FloatStorage, KEY, location, numel)`.
//!
//! The pickle machine here knows only the opcodes such a pickle uses (with the few of
//! protocol 4 that other writers emit for the same objects), and calls only
//! `collections.OrderedDict`, `_rebuild_tensor_v2` and `_rebuild_parameter`, by name,
//! never imported. Its objects live in one arena addressed by index, so a memo entry
//! fetched twice is shared, never copied: a pickle that doubles an entry forty times
//! costs forty small tuples. Bounds ([`limits`]): the pickle's size, the nesting depth
//! of containers and marks, the memo's entries, and the total objects and bytes the
//! machine holds. The result must be a dict from names to tensors: any other entry is
//! refused by name.
//!
//! Files: `tensor` (what is read), `machine` (the pickle), `archive` (the zip).

mod archive;
mod machine;
mod tensor;
#[cfg(test)]
mod tests;

use crate::error::{Error, Result};
use std::path::Path;

pub(crate) use self::machine::parse_state_dict_pickle;
pub use self::{
    archive::TorchZip,
    tensor::{TorchDType, TorchTensor},
};

/// Opens a `torch.save` file ([`TorchZip::new`]).
pub fn open(path: &Path) -> Result<TorchZip<std::fs::File>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    TorchZip::new(f, path)
}
