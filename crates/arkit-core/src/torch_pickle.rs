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

use crate::error::{Error, Result};
use crate::limits;
use std::collections::HashMap;
use std::io::{Read, Seek};
use std::path::{Path, PathBuf};

/// The element type of a stored tensor, from its storage's class
/// (`torch.FloatStorage` and so on).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TorchDType {
    /// `torch.float64` (`DoubleStorage`).
    F64,
    /// `torch.float32` (`FloatStorage`).
    F32,
    /// `torch.float16` (`HalfStorage`).
    F16,
    /// `torch.bfloat16` (`BFloat16Storage`).
    BF16,
    /// `torch.int64` (`LongStorage`).
    I64,
    /// `torch.int32` (`IntStorage`).
    I32,
    /// `torch.int16` (`ShortStorage`).
    I16,
    /// `torch.int8` (`CharStorage`).
    I8,
    /// `torch.uint8` (`ByteStorage`).
    U8,
    /// `torch.bool` (`BoolStorage`).
    Bool,
}

impl TorchDType {
    fn from_storage(name: &str) -> Option<Self> {
        Some(match name {
            "DoubleStorage" => Self::F64,
            "FloatStorage" => Self::F32,
            "HalfStorage" => Self::F16,
            "BFloat16Storage" => Self::BF16,
            "LongStorage" => Self::I64,
            "IntStorage" => Self::I32,
            "ShortStorage" => Self::I16,
            "CharStorage" => Self::I8,
            "ByteStorage" => Self::U8,
            "BoolStorage" => Self::Bool,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Self::F64 | Self::I64 => 8,
            Self::F32 | Self::I32 => 4,
            Self::F16 | Self::BF16 | Self::I16 => 2,
            Self::I8 | Self::U8 | Self::Bool => 1,
        }
    }

    /// PyTorch's name (`torch.float32`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Self::F64 => "torch.float64",
            Self::F32 => "torch.float32",
            Self::F16 => "torch.float16",
            Self::BF16 => "torch.bfloat16",
            Self::I64 => "torch.int64",
            Self::I32 => "torch.int32",
            Self::I16 => "torch.int16",
            Self::I8 => "torch.int8",
            Self::U8 => "torch.uint8",
            Self::Bool => "torch.bool",
        }
    }
}

/// One tensor of a `state_dict`, as the pickle describes it (its data not read yet).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TorchTensor {
    /// The entry's name (`layer.0.weight`).
    pub name: String,
    /// Element type.
    pub dtype: TorchDType,
    /// Shape.
    pub shape: Vec<usize>,
    /// Strides, in elements.
    pub stride: Vec<usize>,
    /// Offset of the first element in its storage, in elements.
    pub offset: usize,
    /// The storage's key (its member is `data/KEY`).
    pub storage: String,
    /// Elements in the storage.
    pub storage_numel: u64,
}

impl TorchTensor {
    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

// ---------------------------------------------------------------------------------------
// The pickle machine.

/// A value on the stack or in a container: scalars inline, everything else an index
/// into the arena.
#[derive(Clone, Copy, Debug)]
enum V {
    None,
    Bool,
    Int(i64),
    Float,
    Obj(u32),
}

#[derive(Debug)]
enum Node {
    Str(String),
    Tuple(Vec<V>),
    List(Vec<V>),
    Dict(Vec<(V, V)>),
    OrderedDictClass,
    RebuildTensor,
    RebuildParameter,
    StorageClass(TorchDType),
    Storage {
        dtype: TorchDType,
        key: String,
        numel: u64,
    },
    Tensor(Box<TensorRef>),
}

#[derive(Debug, Clone)]
struct TensorRef {
    dtype: TorchDType,
    shape: Vec<usize>,
    stride: Vec<usize>,
    offset: usize,
    storage: String,
    storage_numel: u64,
}

struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    source: &'a Path,
    nodes: Vec<Node>,
    depth: Vec<u16>,
    stack: Vec<V>,
    marks: Vec<usize>,
    memo: HashMap<u32, V>,
    /// Bytes the machine holds (arena, stack, strings), against [`limits::MAX_PICKLE_ALLOC_BYTES`].
    held: u64,
    storages: HashMap<String, (TorchDType, u64)>,
}

fn kind(m: &Machine, v: V) -> &'static str {
    match v {
        V::None => "None",
        V::Bool => "a bool",
        V::Int(_) => "an integer",
        V::Float => "a float",
        V::Obj(i) => match &m.nodes[i as usize] {
            Node::Str(_) => "a string",
            Node::Tuple(_) => "a tuple",
            Node::List(_) => "a list",
            Node::Dict(_) => "a dict",
            Node::OrderedDictClass
            | Node::RebuildTensor
            | Node::RebuildParameter
            | Node::StorageClass(_) => "a class or function",
            Node::Storage { .. } => "a bare storage",
            Node::Tensor(_) => "a tensor",
        },
    }
}

impl<'a> Machine<'a> {
    fn err(&self, msg: impl std::fmt::Display) -> Error {
        Error::format(self.source, format!("data.pkl, byte {}: {msg}", self.pos))
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.data.len())
            .ok_or_else(|| self.err("the pickle ends in the middle of an opcode (truncated)"))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }

    fn u32(&mut self) -> Result<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn charge(&mut self, bytes: u64) -> Result<()> {
        self.held += bytes;
        if self.held > limits::MAX_PICKLE_ALLOC_BYTES {
            return Err(self.err(format!(
                "the pickle builds more than {} bytes of objects: not a state_dict",
                limits::MAX_PICKLE_ALLOC_BYTES
            )));
        }
        Ok(())
    }

    fn push(&mut self, v: V) -> Result<()> {
        self.charge(16)?;
        self.stack.push(v);
        Ok(())
    }

    fn pop(&mut self) -> Result<V> {
        let floor = self.marks.last().copied().unwrap_or(0);
        if self.stack.len() <= floor {
            return Err(self.err("an opcode takes a value from an empty stack"));
        }
        Ok(self.stack.pop().expect("checked"))
    }

    fn top_mut(&mut self) -> Result<V> {
        let floor = self.marks.last().copied().unwrap_or(0);
        if self.stack.len() <= floor {
            return Err(self.err("an opcode needs a value on an empty stack"));
        }
        Ok(*self.stack.last().expect("checked"))
    }

    /// Pops everything above the last mark, and the mark.
    fn pop_mark(&mut self) -> Result<Vec<V>> {
        let m = self
            .marks
            .pop()
            .ok_or_else(|| self.err("an opcode needs a MARK that is not there"))?;
        Ok(self.stack.split_off(m))
    }

    fn depth_of(&self, v: V) -> u16 {
        match v {
            V::Obj(i) => self.depth[i as usize],
            _ => 0,
        }
    }

    fn new_node(&mut self, node: Node, depth: u16) -> Result<V> {
        if depth as usize > limits::MAX_PICKLE_DEPTH {
            return Err(self.err(format!(
                "containers nested more than {} deep: not a state_dict",
                limits::MAX_PICKLE_DEPTH
            )));
        }
        if self.nodes.len() >= limits::MAX_PICKLE_OBJECTS {
            return Err(self.err(format!(
                "more than {} objects: not a state_dict",
                limits::MAX_PICKLE_OBJECTS
            )));
        }
        let extra = match &node {
            Node::Str(s) => s.len() as u64,
            Node::Tuple(v) | Node::List(v) => 16 * v.len() as u64,
            Node::Tensor(t) => 16 * (t.shape.len() + t.stride.len()) as u64 + 64,
            _ => 0,
        };
        self.charge(48 + extra)?;
        self.nodes.push(node);
        self.depth.push(depth);
        Ok(V::Obj((self.nodes.len() - 1) as u32))
    }

    fn container(&mut self, items: Vec<V>, list: bool) -> Result<V> {
        let d = items.iter().map(|&v| self.depth_of(v)).max().unwrap_or(0) + 1;
        let node = if list {
            Node::List(items)
        } else {
            Node::Tuple(items)
        };
        self.new_node(node, d)
    }

    fn string(&mut self, n: usize) -> Result<V> {
        let b = self.take(n)?;
        let s = std::str::from_utf8(b)
            .map_err(|_| self.err("a string that is not UTF-8"))?
            .to_string();
        self.new_node(Node::Str(s), 0)
    }

    fn line(&mut self) -> Result<&'a str> {
        let rest = &self.data[self.pos..];
        let n = rest
            .iter()
            .take(256)
            .position(|&b| b == b'\n')
            .ok_or_else(|| self.err("a GLOBAL name longer than 256 bytes or unterminated"))?;
        let s = std::str::from_utf8(&rest[..n])
            .map_err(|_| self.err("a GLOBAL name that is not UTF-8"))?;
        self.pos += n + 1;
        Ok(s)
    }

    fn global(&mut self, module: &str, name: &str) -> Result<V> {
        let node = match (module, name) {
            ("collections", "OrderedDict") => Node::OrderedDictClass,
            ("torch._utils", "_rebuild_tensor_v2") => Node::RebuildTensor,
            ("torch._utils", "_rebuild_parameter") => Node::RebuildParameter,
            ("torch", s) if TorchDType::from_storage(s).is_some() => {
                Node::StorageClass(TorchDType::from_storage(s).expect("checked"))
            }
            _ => {
                return Err(self.err(format!(
                    "the pickle refers to {module}.{name}, which a torch.save(state_dict) never does (refused; nothing from the file is run)"
                )));
            }
        };
        self.new_node(node, 0)
    }

    fn node(&self, v: V) -> Option<&Node> {
        match v {
            V::Obj(i) => Some(&self.nodes[i as usize]),
            _ => None,
        }
    }

    fn str_of(&self, v: V) -> Option<&str> {
        match self.node(v) {
            Some(Node::Str(s)) => Some(s),
            _ => None,
        }
    }

    fn usize_tuple(&self, v: V, what: &str) -> Result<Vec<usize>> {
        let Some(Node::Tuple(items)) = self.node(v) else {
            return Err(self.err(format!("a tensor's {what} is not a tuple")));
        };
        items
            .iter()
            .map(|x| match x {
                V::Int(i) if *i >= 0 => usize::try_from(*i)
                    .map_err(|_| self.err(format!("a tensor's {what} is too large"))),
                _ => Err(self.err(format!(
                    "a tensor's {what} holds a value that is not a size"
                ))),
            })
            .collect()
    }

    fn persistent_load(&mut self, pid: V) -> Result<V> {
        let bad =
            |m: &Self| m.err("a persistent id that is not ('storage', type, key, location, numel)");
        let Some(Node::Tuple(t)) = self.node(pid) else {
            return Err(bad(self));
        };
        let t = t.clone();
        if t.len() != 5 || self.str_of(t[0]) != Some("storage") {
            return Err(bad(self));
        }
        let Some(Node::StorageClass(dtype)) = self.node(t[1]) else {
            return Err(bad(self));
        };
        let dtype = *dtype;
        let key = self.str_of(t[2]).ok_or_else(|| bad(self))?.to_string();
        if self.str_of(t[3]).is_none() {
            return Err(bad(self));
        }
        let V::Int(numel) = t[4] else {
            return Err(bad(self));
        };
        if key.is_empty()
            || key.len() > 64
            || !key.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
        {
            return Err(self.err(format!("a storage key {key:?} that is not a plain name")));
        }
        let numel = u64::try_from(numel).map_err(|_| self.err("a storage with a negative size"))?;
        let bytes = numel.checked_mul(dtype.size() as u64);
        if bytes.is_none_or(|b| b > limits::MAX_TORCH_STORAGE_BYTES) {
            return Err(self.err(format!(
                "storage {key} declares {numel} elements of {}, more than the {} bytes allowed per storage",
                dtype.name(),
                limits::MAX_TORCH_STORAGE_BYTES
            )));
        }
        if let Some(&(d, n)) = self.storages.get(&key) {
            if (d, n) != (dtype, numel) {
                return Err(self.err(format!("storage {key} is declared twice, differently")));
            }
        } else {
            if self.storages.len() >= limits::MAX_TORCH_TENSORS {
                return Err(self.err(format!("more than {} storages", limits::MAX_TORCH_TENSORS)));
            }
            self.storages.insert(key.clone(), (dtype, numel));
        }
        self.new_node(Node::Storage { dtype, key, numel }, 0)
    }

    fn reduce(&mut self, callable: V, args: V) -> Result<V> {
        let Some(Node::Tuple(a)) = self.node(args) else {
            return Err(self.err("REDUCE with arguments that are not a tuple"));
        };
        let a = a.clone();
        match self.node(callable) {
            Some(Node::OrderedDictClass) => {
                if !a.is_empty() {
                    return Err(self.err("OrderedDict called with arguments"));
                }
                self.new_node(Node::Dict(Vec::new()), 1)
            }
            Some(Node::RebuildTensor) => {
                if !(6..=7).contains(&a.len()) {
                    return Err(self.err(format!(
                        "_rebuild_tensor_v2 with {} arguments, not 6 or 7",
                        a.len()
                    )));
                }
                let Some(Node::Storage { dtype, key, numel }) = self.node(a[0]) else {
                    return Err(self.err("_rebuild_tensor_v2 of something that is not a storage"));
                };
                let (dtype, key, numel) = (*dtype, key.clone(), *numel);
                let V::Int(offset) = a[1] else {
                    return Err(self.err("a tensor's offset is not an integer"));
                };
                let offset = usize::try_from(offset)
                    .map_err(|_| self.err("a tensor's offset is negative"))?;
                let shape = self.usize_tuple(a[2], "size")?;
                let stride = self.usize_tuple(a[3], "stride")?;
                if shape.len() != stride.len() {
                    return Err(self.err("a tensor's size and stride differ in length"));
                }
                if !matches!(a[4], V::Bool) {
                    return Err(self.err("a tensor's requires_grad is not a bool"));
                }
                for &x in &a[5..] {
                    if !matches!(self.node(x), Some(Node::Dict(_))) {
                        return Err(self.err("a tensor's hooks or metadata are not a dict"));
                    }
                }
                // The last element the view reaches must lie in the storage.
                let mut numel_view: u64 = 1;
                let mut last: u64 = offset as u64;
                for (&n, &s) in shape.iter().zip(&stride) {
                    numel_view = numel_view.saturating_mul(n as u64);
                    last =
                        last.saturating_add((n as u64).saturating_sub(1).saturating_mul(s as u64));
                }
                if numel_view > 0 && last >= numel {
                    return Err(self.err(format!(
                        "a tensor of size {shape:?} (stride {stride:?}, offset {offset}) reaches beyond its storage {key} of {numel} elements"
                    )));
                }
                let d = self.depth_of(a[2]).max(self.depth_of(a[3])) + 1;
                self.new_node(
                    Node::Tensor(Box::new(TensorRef {
                        dtype,
                        shape,
                        stride,
                        offset,
                        storage: key,
                        storage_numel: numel,
                    })),
                    d,
                )
            }
            Some(Node::RebuildParameter) => {
                if a.len() != 3 || !matches!(self.node(a[0]), Some(Node::Tensor(_))) {
                    return Err(self.err("_rebuild_parameter of something that is not a tensor"));
                }
                Ok(a[0])
            }
            _ => Err(self.err(format!(
                "REDUCE calls {}, which a torch.save(state_dict) never does",
                kind(self, callable)
            ))),
        }
    }

    fn set_items(&mut self, target: V, items: Vec<V>) -> Result<()> {
        if !items.len().is_multiple_of(2) {
            return Err(self.err("SETITEMS with an odd number of values"));
        }
        let d = items.iter().map(|&v| self.depth_of(v)).max().unwrap_or(0) + 1;
        if d as usize > limits::MAX_PICKLE_DEPTH {
            return Err(self.err(format!(
                "containers nested more than {} deep: not a state_dict",
                limits::MAX_PICKLE_DEPTH
            )));
        }
        self.charge(16 * items.len() as u64)?;
        let V::Obj(i) = target else {
            return Err(self.err("SETITEM on something that is not a dict"));
        };
        let i = i as usize;
        let Node::Dict(entries) = &mut self.nodes[i] else {
            return Err(self.err("SETITEM on something that is not a dict"));
        };
        entries.extend(items.chunks_exact(2).map(|p| (p[0], p[1])));
        self.depth[i] = self.depth[i].max(d);
        Ok(())
    }

    fn append(&mut self, target: V, items: Vec<V>) -> Result<()> {
        let d = items.iter().map(|&v| self.depth_of(v)).max().unwrap_or(0) + 1;
        if d as usize > limits::MAX_PICKLE_DEPTH {
            return Err(self.err(format!(
                "containers nested more than {} deep: not a state_dict",
                limits::MAX_PICKLE_DEPTH
            )));
        }
        self.charge(16 * items.len() as u64)?;
        let V::Obj(i) = target else {
            return Err(self.err("APPEND on something that is not a list"));
        };
        let i = i as usize;
        let Node::List(list) = &mut self.nodes[i] else {
            return Err(self.err("APPEND on something that is not a list"));
        };
        list.extend(items);
        self.depth[i] = self.depth[i].max(d);
        Ok(())
    }

    fn memo_put(&mut self, k: u32) -> Result<()> {
        let v = self.top_mut()?;
        if !self.memo.contains_key(&k) && self.memo.len() >= limits::MAX_PICKLE_MEMO {
            return Err(self.err(format!(
                "more than {} memo entries: not a state_dict",
                limits::MAX_PICKLE_MEMO
            )));
        }
        self.charge(32)?;
        self.memo.insert(k, v);
        Ok(())
    }

    fn memo_get(&mut self, k: u32) -> Result<()> {
        let v = *self
            .memo
            .get(&k)
            .ok_or_else(|| self.err(format!("memo entry {k} is read before it is written")))?;
        self.push(v)
    }

    /// Runs the pickle program to its `STOP`. Long (over 150 lines) on purpose: one
    /// `match` over the opcodes a `torch.save` state dict uses, each arm a few lines
    /// against the stack and memo; anything else is refused by name.
    fn run(&mut self) -> Result<V> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    // PROTO
                    let p = self.u8()?;
                    if p > 5 {
                        return Err(self.err(format!("pickle protocol {p} is unknown")));
                    }
                }
                0x95 => {
                    // FRAME: a hint of the next frame's length; nothing to do.
                    self.take(8)?;
                }
                b'.' => return self.pop(),
                b'(' => {
                    if self.marks.len() >= limits::MAX_PICKLE_DEPTH {
                        return Err(self.err(format!(
                            "marks nested more than {} deep: not a state_dict",
                            limits::MAX_PICKLE_DEPTH
                        )));
                    }
                    self.marks.push(self.stack.len());
                }
                b'0' => {
                    self.pop()?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    let v = self.global(module, name)?;
                    self.push(v)?;
                }
                0x93 => {
                    // STACK_GLOBAL
                    let name = self.pop()?;
                    let module = self.pop()?;
                    let (Some(m), Some(n)) = (self.str_of(module), self.str_of(name)) else {
                        return Err(self.err("STACK_GLOBAL of values that are not strings"));
                    };
                    let (m, n) = (m.to_string(), n.to_string());
                    let v = self.global(&m, &n)?;
                    self.push(v)?;
                }
                b'q' => {
                    let k = self.u8()? as u32;
                    self.memo_put(k)?;
                }
                b'r' => {
                    let k = self.u32()?;
                    self.memo_put(k)?;
                }
                0x94 => {
                    let k = self.memo.len() as u32;
                    self.memo_put(k)?;
                }
                b'h' => {
                    let k = self.u8()? as u32;
                    self.memo_get(k)?;
                }
                b'j' => {
                    let k = self.u32()?;
                    self.memo_get(k)?;
                }
                b'}' => {
                    let v = self.new_node(Node::Dict(Vec::new()), 1)?;
                    self.push(v)?;
                }
                b']' => {
                    let v = self.new_node(Node::List(Vec::new()), 1)?;
                    self.push(v)?;
                }
                b')' => {
                    let v = self.new_node(Node::Tuple(Vec::new()), 1)?;
                    self.push(v)?;
                }
                b't' => {
                    let items = self.pop_mark()?;
                    let v = self.container(items, false)?;
                    self.push(v)?;
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let mut items = vec![V::None; n];
                    for slot in items.iter_mut().rev() {
                        *slot = self.pop()?;
                    }
                    let v = self.container(items, false)?;
                    self.push(v)?;
                }
                b'J' => {
                    let v = self.u32()? as i32;
                    self.push(V::Int(v as i64))?;
                }
                b'K' => {
                    let v = self.u8()?;
                    self.push(V::Int(v as i64))?;
                }
                b'M' => {
                    let b = self.take(2)?;
                    self.push(V::Int(u16::from_le_bytes([b[0], b[1]]) as i64))?;
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes.
                    let n = self.u8()? as usize;
                    if n > 8 {
                        return Err(self.err("an integer wider than 64 bits"));
                    }
                    let b = self.take(n)?;
                    let mut buf = if b.last().is_some_and(|&x| x & 0x80 != 0) {
                        [0xffu8; 8]
                    } else {
                        [0u8; 8]
                    };
                    buf[..n].copy_from_slice(b);
                    self.push(V::Int(i64::from_le_bytes(buf)))?;
                }
                b'N' => self.push(V::None)?,
                0x88 | 0x89 => self.push(V::Bool)?,
                b'G' => {
                    self.take(8)?;
                    self.push(V::Float)?;
                }
                b'X' => {
                    let n = self.u32()? as usize;
                    let v = self.string(n)?;
                    self.push(v)?;
                }
                0x8c => {
                    let n = self.u8()? as usize;
                    let v = self.string(n)?;
                    self.push(v)?;
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let v = self.persistent_load(pid)?;
                    self.push(v)?;
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let v = self.reduce(callable, args)?;
                    self.push(v)?;
                }
                b'b' => {
                    // BUILD: only an OrderedDict's attributes (its `_metadata`), ignored.
                    let state = self.pop()?;
                    let obj = self.top_mut()?;
                    if !matches!(self.node(obj), Some(Node::Dict(_)))
                        || !matches!(self.node(state), Some(Node::Dict(_)) | None)
                    {
                        return Err(self.err(format!(
                            "BUILD of {} with {}: only an OrderedDict's attributes are expected",
                            kind(self, obj),
                            kind(self, state)
                        )));
                    }
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    let target = self.top_mut()?;
                    self.set_items(target, vec![k, v])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let target = self.top_mut()?;
                    self.set_items(target, items)?;
                }
                b'a' => {
                    let v = self.pop()?;
                    let target = self.top_mut()?;
                    self.append(target, vec![v])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let target = self.top_mut()?;
                    self.append(target, items)?;
                }
                _ => {
                    self.pos -= 1;
                    return Err(self.err(format!(
                        "opcode 0x{op:02x} is not one that torch.save writes for a state_dict"
                    )));
                }
            }
        }
    }
}

/// Reads the pickle of a `state_dict` (`data.pkl`) into its tensors' descriptions, in
/// the file's order. `source` names the file in errors.
///
/// Refused: a pickle longer than [`limits::MAX_PICKLE_BYTES`], deeper than
/// [`limits::MAX_PICKLE_DEPTH`], with more than [`limits::MAX_PICKLE_MEMO`] memo entries
/// or [`limits::MAX_PICKLE_OBJECTS`] objects or [`limits::MAX_PICKLE_ALLOC_BYTES`]
/// bytes of them; any opcode or callable that a `state_dict` does not use; a result
/// that is not a dict of tensors (an entry that is not a tensor is named), a name
/// given twice, more than [`limits::MAX_TORCH_TENSORS`] tensors, a tensor reaching
/// beyond its storage.
pub(crate) fn parse_state_dict_pickle(data: &[u8], source: &Path) -> Result<Vec<TorchTensor>> {
    if data.len() as u64 > limits::MAX_PICKLE_BYTES {
        return Err(Error::format(
            source,
            format!(
                "data.pkl is {} bytes, more than the {} allowed",
                data.len(),
                limits::MAX_PICKLE_BYTES
            ),
        ));
    }
    let mut m = Machine {
        data,
        pos: 0,
        source,
        nodes: Vec::new(),
        depth: Vec::new(),
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        held: 0,
        storages: HashMap::new(),
    };
    let result = m.run()?;
    let Some(Node::Dict(entries)) = m.node(result) else {
        return Err(Error::format(
            source,
            format!(
                "the pickle holds {}, not a state_dict (a dict of tensors)",
                kind(&m, result)
            ),
        ));
    };
    if entries.len() > limits::MAX_TORCH_TENSORS {
        return Err(Error::format(
            source,
            format!(
                "{} entries, more than the {} allowed",
                entries.len(),
                limits::MAX_TORCH_TENSORS
            ),
        ));
    }
    let mut out = Vec::with_capacity(entries.len());
    let mut seen = std::collections::HashSet::new();
    for &(k, v) in entries {
        let Some(name) = m.str_of(k) else {
            return Err(Error::format(
                source,
                format!(
                    "the state_dict has a key that is {}, not a name",
                    kind(&m, k)
                ),
            ));
        };
        let Some(Node::Tensor(t)) = m.node(v) else {
            return Err(Error::format(
                source,
                format!(
                    "entry '{name}' is {}, not a tensor: a state_dict of the network holds tensors only",
                    kind(&m, v)
                ),
            ));
        };
        if !seen.insert(name.to_string()) {
            return Err(Error::format(
                source,
                format!("entry '{name}' is given twice"),
            ));
        }
        out.push(TorchTensor {
            name: name.to_string(),
            dtype: t.dtype,
            shape: t.shape.clone(),
            stride: t.stride.clone(),
            offset: t.offset,
            storage: t.storage.clone(),
            storage_numel: t.storage_numel,
        });
    }
    Ok(out)
}

// ---------------------------------------------------------------------------------------
// The zip archive.

/// A `torch.save` zip archive whose pickle has been read and checked; the tensors'
/// data are read one at a time by [`TorchZip::read`].
pub struct TorchZip<R: Read + Seek> {
    zip: zip::ZipArchive<R>,
    source: PathBuf,
    prefix: String,
    tensors: Vec<TorchTensor>,
}

impl std::fmt::Debug for TorchZip<std::fs::File> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "TorchZip({}, {} tensors)",
            self.source.display(),
            self.tensors.len()
        )
    }
}

/// Reads member `name` whole, refusing it when it holds more than `max` bytes; the
/// size the directory claims is used only to refuse early, never to allocate.
fn read_member<R: Read + Seek>(
    zip: &mut zip::ZipArchive<R>,
    name: &str,
    max: u64,
    source: &Path,
) -> Result<Vec<u8>> {
    let member = format!("{}:{name}", source.display());
    let f = zip
        .by_name(name)
        .map_err(|e| Error::format(&member, format!("cannot open the member: {e}")))?;
    if f.size() > max {
        return Err(Error::format(
            &member,
            format!("{} bytes, more than the {max} expected", f.size()),
        ));
    }
    let mut out = Vec::new();
    f.take(max + 1).read_to_end(&mut out).map_err(|e| {
        Error::format(
            &member,
            format!("cannot read the member (truncated or corrupt): {e}"),
        )
    })?;
    if out.len() as u64 > max {
        return Err(Error::format(
            &member,
            format!("more than the {max} bytes expected"),
        ));
    }
    Ok(out)
}

impl<R: Read + Seek> TorchZip<R> {
    /// Opens a `torch.save` archive: finds its `data.pkl`, reads it with
    /// `parse_state_dict_pickle`, checks the byte order and that every storage's
    /// member exists with exactly the bytes its tensors need. No tensor data is read.
    pub fn new(reader: R, source: &Path) -> Result<Self> {
        let mut zip = zip::ZipArchive::new(reader).map_err(|e| {
            Error::format(
                source,
                format!(
                    "not a PyTorch state_dict (torch.save zip format): not a valid zip archive: {e}"
                ),
            )
        })?;
        if zip.len() > limits::MAX_TORCH_TENSORS + 16 {
            return Err(Error::format(
                source,
                format!(
                    "{} members, more than a state_dict of at most {} tensors has",
                    zip.len(),
                    limits::MAX_TORCH_TENSORS
                ),
            ));
        }
        let pkls: Vec<String> = zip
            .file_names()
            .filter_map(|n| n.ok().map(|n| n.into_owned()))
            .filter(|n| n.ends_with("/data.pkl") && n.matches('/').count() == 1)
            .collect();
        let [pkl] = pkls.as_slice() else {
            return Err(Error::format(
                source,
                format!(
                    "not a PyTorch state_dict (torch.save zip format): {} members FOLDER/data.pkl, not one",
                    pkls.len()
                ),
            ));
        };
        let prefix = pkl.strip_suffix("data.pkl").expect("checked").to_string();
        let bo = format!("{prefix}byteorder");
        if zip.index_for_name(&bo).is_some() {
            let order = read_member(&mut zip, &bo, 16, source)?;
            if order != b"little" {
                return Err(Error::format(
                    source,
                    format!(
                        "byte order {:?}: only little-endian checkpoints are read",
                        String::from_utf8_lossy(&order)
                    ),
                ));
            }
        }
        let pickle = read_member(&mut zip, pkl, limits::MAX_PICKLE_BYTES, source)?;
        let tensors = parse_state_dict_pickle(&pickle, source)?;
        drop(pickle);
        let mut total = 0u64;
        let mut checked = std::collections::HashSet::new();
        for t in &tensors {
            if !checked.insert(t.storage.clone()) {
                continue;
            }
            let name = format!("{prefix}data/{}", t.storage);
            let member = format!("{}:{name}", source.display());
            let want = t.storage_numel * t.dtype.size() as u64;
            let f = zip.by_name(&name).map_err(|e| {
                Error::format(
                    &member,
                    format!("the storage of '{}' is missing: {e}", t.name),
                )
            })?;
            if f.size() != want {
                return Err(Error::format(
                    &member,
                    format!(
                        "{} bytes, but '{}' declares {} elements of {} ({want} bytes)",
                        f.size(),
                        t.name,
                        t.storage_numel,
                        t.dtype.name()
                    ),
                ));
            }
            total += want;
            if total > limits::MAX_TORCH_DATA_BYTES {
                return Err(Error::format(
                    source,
                    format!(
                        "the tensors hold more than the {} bytes allowed",
                        limits::MAX_TORCH_DATA_BYTES
                    ),
                ));
            }
        }
        Ok(Self {
            zip,
            source: source.to_path_buf(),
            prefix,
            tensors,
        })
    }

    /// The tensors, in the file's order.
    pub fn tensors(&self) -> &[TorchTensor] {
        &self.tensors
    }

    /// The data of tensor `i` ([`TorchTensor`] of [`Self::tensors`]), contiguous
    /// (row-major) little-endian bytes, `numel * dtype.size()` of them. Reads its
    /// storage's member (at most `limits::MAX_TORCH_STORAGE_BYTES`).
    pub fn read(&mut self, i: usize) -> Result<Vec<u8>> {
        let t = self.tensors[i].clone();
        let size = t.dtype.size();
        let want = t.storage_numel * size as u64;
        let name = format!("{}data/{}", self.prefix, t.storage);
        let storage = read_member(&mut self.zip, &name, want, &self.source)?;
        if storage.len() as u64 != want {
            return Err(Error::format(
                format!("{}:{name}", self.source.display()),
                format!("{} bytes, {want} expected (truncated)", storage.len()),
            ));
        }
        let numel = t.numel();
        // Row-major strides: a slice of the storage.
        let mut contiguous = true;
        let mut expect = 1usize;
        for (&n, &s) in t.shape.iter().zip(&t.stride).rev() {
            if n > 1 && s != expect {
                contiguous = false;
            }
            expect = expect.saturating_mul(n);
        }
        if numel == 0 {
            return Ok(Vec::new());
        }
        if contiguous {
            let a = t.offset * size;
            return Ok(storage[a..a + numel * size].to_vec());
        }
        let mut out = Vec::with_capacity(numel * size);
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..numel {
            let e = t.offset + idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum::<usize>();
            out.extend_from_slice(&storage[e * size..(e + 1) * size]);
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < t.shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Ok(out)
    }
}

/// Opens a `torch.save` file ([`TorchZip::new`]).
pub fn open(path: &Path) -> Result<TorchZip<std::fs::File>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    TorchZip::new(f, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn seed(name: &str) -> PathBuf {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../fuzz/corpus/torch_pickle")
            .join(name)
    }

    fn f32s(b: &[u8]) -> Vec<f32> {
        b.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }

    fn refused(data: &[u8]) -> String {
        let t = Instant::now();
        let e = parse_state_dict_pickle(data, Path::new("x.pth"))
            .expect_err("refused")
            .to_string();
        assert!(
            t.elapsed() < Duration::from_secs(1),
            "{e}: {:?}",
            t.elapsed()
        );
        assert!(e.starts_with("x.pth"), "{e}");
        e
    }

    /// A file written by `torch.save` (torch 2.x; tests/python/torch_pickle_seeds.py):
    /// names in order, types, shapes and every value, a transposed view read through
    /// its strides.
    #[test]
    fn a_torch_saved_state_dict_reads_value_for_value() {
        let mut z = open(&seed("real.pth")).unwrap();
        let names: Vec<&str> = z.tensors().iter().map(|t| t.name.as_str()).collect();
        assert_eq!(names, ["a.weight", "a.num_batches_tracked", "b", "c.half"]);
        let t = &z.tensors()[2];
        assert_eq!(
            (t.dtype, t.shape.as_slice(), t.stride.as_slice()),
            (TorchDType::F32, &[4, 3][..], &[1, 4][..])
        );
        assert_eq!(f32s(&z.read(0).unwrap()), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(z.tensors()[1].dtype, TorchDType::I64);
        assert!(z.tensors()[1].shape.is_empty());
        assert_eq!(z.read(1).unwrap(), 7i64.to_le_bytes());
        // b = arange(12).reshape(3, 4).t(): b[i][j] = 4 j + i.
        let want: Vec<f32> = (0..4)
            .flat_map(|i| (0..3).map(move |j| (4 * j + i) as f32))
            .collect();
        assert_eq!(f32s(&z.read(2).unwrap()), want);
        assert_eq!(z.tensors()[3].dtype, TorchDType::F16);
        // float16 1.5 = 0x3e00, -2.0 = 0xc000.
        assert_eq!(z.read(3).unwrap(), [0x00, 0x3e, 0x00, 0xc0]);
    }

    #[test]
    fn a_module_state_dict_with_metadata_reads() {
        let z = open(&seed("module.pth")).unwrap();
        let names: Vec<&str> = z.tensors().iter().map(|t| t.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "0.weight",
                "0.bias",
                "1.weight",
                "1.bias",
                "1.running_mean",
                "1.running_var",
                "1.num_batches_tracked"
            ]
        );
        assert_eq!(z.tensors()[0].shape, [3, 2, 1]);
    }

    /// 10^6 nested tuples (1 MB, which overflowed the stack of a recursive reader) and
    /// 10^6 nested marks: refused at the depth limit, at once.
    #[test]
    fn deep_nesting_is_refused_at_the_limit() {
        let mut p = b"\x80\x02)".to_vec();
        p.extend(std::iter::repeat_n(0x85u8, 1_000_000));
        p.push(b'.');
        let e = refused(&p);
        assert!(e.contains("nested more than 32 deep"), "{e}");
        let mut p = b"\x80\x02".to_vec();
        p.extend(std::iter::repeat_n(b'(', 1_000_000));
        let e = refused(&p);
        assert!(e.contains("marks nested more than 32 deep"), "{e}");
        // Just at the limit is read (and refused for what it is, not for its depth).
        let mut p = b"\x80\x02)".to_vec();
        p.extend(std::iter::repeat_n(0x85u8, 31));
        p.push(b'.');
        assert!(refused(&p).contains("holds a tuple, not a state_dict"));
    }

    /// A memo entry replaced by a pair of itself 40 times (2^40 leaves if copied, as
    /// candle's reader did) costs 40 tuples; a million times is refused by the depth
    /// bound; as a dict entry it is named.
    #[test]
    fn memo_doubling_is_shared_not_copied() {
        let double = |n: usize| {
            let mut p = b"\x80\x02X\x01\x00\x00\x00aq\x000".to_vec();
            for _ in 0..n {
                p.extend(b"h\x00h\x00\x86q\x000");
            }
            p.extend(b"h\x00");
            p
        };
        let mut p = double(20);
        p.push(b'.');
        assert!(refused(&p).contains("holds a tuple"));
        let mut p = double(1_000_000);
        p.push(b'.');
        assert!(refused(&p).contains("nested more than 32 deep"));
        // In a dict: X = {'w': <20-fold doubled tuple>}.
        let mut p = b"\x80\x02}q\x01X\x01\x00\x00\x00w".to_vec();
        p.extend(&double(20)[2..]);
        p.extend(b"s.");
        let e = refused(&p);
        assert!(e.contains("entry 'w' is a tuple, not a tensor"), "{e}");
    }

    /// Pushing one memo entry millions of times hits the allocation bound.
    #[test]
    fn the_allocation_bound_holds() {
        let mut p = b"\x80\x02Nq\x00".to_vec();
        for _ in 0..5_000_000 {
            p.extend(b"h\x00");
        }
        p.push(b'.');
        let e = refused(&p);
        assert!(e.contains("more than 67108864 bytes of objects"), "{e}");
    }

    /// An entry that is not a tensor is named; so is a global outside the subset, and
    /// a tensor reaching beyond its storage.
    #[test]
    fn what_is_not_a_state_dict_is_named() {
        let e = open(&seed("non_tensor_entry.pth")).unwrap_err().to_string();
        assert!(
            e.contains("entry 'epoch' is an integer, not a tensor"),
            "{e}"
        );
        let e = refused(b"\x80\x02cos\nsystem\nX\x02\x00\x00\x00ls\x85R.");
        assert!(e.contains("refers to os.system"), "{e}");
        let e = open(&seed("beyond_storage.pth")).unwrap_err().to_string();
        assert!(
            e.contains("reaches beyond its storage 0 of 2 elements"),
            "{e}"
        );
        let e = open(&seed("memo_doubling.pth")).unwrap_err().to_string();
        assert!(e.contains("nested more than 32 deep"), "{e}");
    }

    /// Every prefix of a real pickle is an error, never a panic.
    #[test]
    fn every_truncation_is_an_error() {
        let p = std::fs::read(seed("module.pkl")).unwrap();
        assert_eq!(
            parse_state_dict_pickle(&p, Path::new("m")).unwrap().len(),
            7
        );
        for n in 0..p.len() {
            assert!(
                parse_state_dict_pickle(&p[..n], Path::new("m")).is_err(),
                "{n}"
            );
        }
    }
}
