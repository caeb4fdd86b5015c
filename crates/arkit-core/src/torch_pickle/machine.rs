//! The pickle machine: the opcodes a `state_dict` pickle uses, one arena of objects
//! addressed by index, and the bounds of [`crate::limits`] checked before each allocation.

use super::tensor::{TorchDType, TorchTensor};
use crate::error::{Error, Result};
use crate::limits;
use std::collections::HashMap;
use std::path::Path;

/// A value on the stack or in a container: scalars inline, everything else an index
/// into the arena.
#[derive(Clone, Copy, Debug)]
pub(super) enum V {
    None,
    Bool,
    Int(i64),
    Float,
    Obj(u32),
}

#[derive(Debug)]
pub(super) enum Node {
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
pub(super) struct TensorRef {
    dtype: TorchDType,
    shape: Vec<usize>,
    stride: Vec<usize>,
    offset: usize,
    storage: String,
    storage_numel: u64,
}

pub(super) struct Machine<'a> {
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

pub(super) fn kind(m: &Machine, v: V) -> &'static str {
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
