//! A minimal protocol-buffers encoder for the part of ONNX's `onnx.proto` (proto2
//! syntax) that an exported inference graph uses: `ModelProto`, `OperatorSetIdProto`,
//! `GraphProto`, `NodeProto`, `AttributeProto`, `TensorProto`, `ValueInfoProto` with
//! its `TypeProto.Tensor` and `TensorShapeProto`, and `StringStringEntryProto`.
//!
//! Wire format (protocol buffers encoding, a fact of the format): each field is a key
//! `(field_number << 3) | wire_type` written as a varint, then its value: wire type 0
//! a varint (integers; a negative `int64` as its 64-bit two's complement, ten bytes),
//! 2 a varint length then that many bytes (strings, bytes, embedded messages), 5 four
//! little-endian bytes (`float`). Repeated scalars are written one key per value (the
//! proto2 default, which every parser reads). Tensor contents go in `raw_data`:
//! the values' little-endian bytes, row-major.
//!
//! The field numbers below are those of `onnx.proto` (onnx/onnx, IR version 8, the IR
//! version of opset 17), stated as facts next to each message.

/// Wire type of varint-encoded fields.
const VARINT: u32 = 0;
/// Wire type of length-delimited fields.
const LEN: u32 = 2;
/// Wire type of 32-bit fields (`float`).
const FIXED32: u32 = 5;

/// `TensorProto.DataType.FLOAT`.
pub(crate) const FLOAT: i32 = 1;
/// `TensorProto.DataType.INT64`.
pub(crate) const INT64: i32 = 7;

/// An encoded message's bytes, built field by field.
#[derive(Debug, Default, Clone)]
pub(crate) struct Message(Vec<u8>);

impl Message {
    /// An empty message.
    pub fn new() -> Self {
        Self::default()
    }

    /// The encoded bytes.
    pub(crate) fn into_bytes(self) -> Vec<u8> {
        self.0
    }

    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push((v as u8 & 0x7f) | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }

    fn key(&mut self, field: u32, wire: u32) {
        self.varint(((field << 3) | wire) as u64);
    }

    /// An `int64` / `int32` / enum field (negative values as 64-bit two's complement).
    pub fn int(&mut self, field: u32, v: i64) -> &mut Self {
        self.key(field, VARINT);
        self.varint(v as u64);
        self
    }

    /// A `float` field.
    pub fn float(&mut self, field: u32, v: f32) -> &mut Self {
        self.key(field, FIXED32);
        self.0.extend_from_slice(&v.to_le_bytes());
        self
    }

    /// A `bytes` field.
    pub fn bytes(&mut self, field: u32, b: &[u8]) -> &mut Self {
        self.key(field, LEN);
        self.varint(b.len() as u64);
        self.0.extend_from_slice(b);
        self
    }

    /// A `string` field.
    pub fn string(&mut self, field: u32, s: &str) -> &mut Self {
        self.bytes(field, s.as_bytes())
    }

    /// An embedded message field.
    pub fn message(&mut self, field: u32, m: &Message) -> &mut Self {
        self.bytes(field, &m.0)
    }
}

/// The dimension of a value's shape: a number or a symbolic name (`dim_param`).
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Dim {
    /// A fixed size.
    Fixed(usize),
    /// A size named by a string, chosen at run time (the batch).
    Named(String),
}

/// `ValueInfoProto` (name = 1, type = 2, doc_string = 3) of a tensor with element type
/// `elem_type` and the given shape: `TypeProto` (tensor_type = 1) ->
/// `TypeProto.Tensor` (elem_type = 1, shape = 2) -> `TensorShapeProto` (dim = 1) ->
/// `Dimension` (dim_value = 1, dim_param = 2).
pub(crate) fn value_info(name: &str, elem_type: i32, dims: &[Dim], doc: &str) -> Message {
    let mut shape = Message::new();
    for d in dims {
        let mut dim = Message::new();
        match d {
            Dim::Fixed(n) => dim.int(1, *n as i64),
            Dim::Named(s) => dim.string(2, s),
        };
        shape.message(1, &dim);
    }
    let mut tensor = Message::new();
    tensor.int(1, elem_type as i64).message(2, &shape);
    let mut ty = Message::new();
    ty.message(1, &tensor);
    let mut vi = Message::new();
    vi.string(1, name).message(2, &ty);
    if !doc.is_empty() {
        vi.string(3, doc);
    }
    vi
}

/// `TensorProto` (dims = 1, data_type = 2, name = 8, raw_data = 9) of `f32` values.
pub(crate) fn tensor_f32(name: &str, dims: &[usize], values: &[f32]) -> Message {
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    tensor_raw(name, dims, FLOAT, &raw)
}

/// `TensorProto` of `i64` values (see [`tensor_f32`]).
pub(crate) fn tensor_i64(name: &str, dims: &[usize], values: &[i64]) -> Message {
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    tensor_raw(name, dims, INT64, &raw)
}

fn tensor_raw(name: &str, dims: &[usize], data_type: i32, raw: &[u8]) -> Message {
    let mut t = Message::new();
    for &d in dims {
        t.int(1, d as i64);
    }
    t.int(2, data_type as i64).string(8, name).bytes(9, raw);
    t
}

/// An attribute's value.
#[derive(Debug, Clone)]
pub(crate) enum Attr {
    /// `AttributeType.FLOAT` (1), field `f` = 2.
    Float(f32),
    /// `AttributeType.INT` (2), field `i` = 3.
    Int(i64),
    /// `AttributeType.STRING` (3), field `s` = 4.
    String(String),
    /// `AttributeType.INTS` (7), field `ints` = 8.
    Ints(Vec<i64>),
}

/// `AttributeProto` (name = 1, type = 20, and the value's field, see [`Attr`]).
pub fn attribute(name: &str, value: &Attr) -> Message {
    let mut a = Message::new();
    a.string(1, name);
    match value {
        Attr::Float(f) => a.float(2, *f).int(20, 1),
        Attr::Int(i) => a.int(3, *i).int(20, 2),
        Attr::String(s) => a.string(4, s).int(20, 3),
        Attr::Ints(v) => {
            for &i in v {
                a.int(8, i);
            }
            a.int(20, 7)
        }
    };
    a
}

/// `NodeProto` (input = 1, output = 2, name = 3, op_type = 4, attribute = 5).
pub fn node(
    op_type: &str,
    name: &str,
    inputs: &[String],
    outputs: &[String],
    attrs: &[(String, Attr)],
) -> Message {
    let mut n = Message::new();
    for i in inputs {
        n.string(1, i);
    }
    for o in outputs {
        n.string(2, o);
    }
    n.string(3, name).string(4, op_type);
    for (k, v) in attrs {
        n.message(5, &attribute(k, v));
    }
    n
}

/// `GraphProto` (node = 1, name = 2, initializer = 5, doc_string = 10, input = 11,
/// output = 12).
pub fn graph(
    name: &str,
    doc: &str,
    nodes: &[Message],
    initializers: &[Message],
    inputs: &[Message],
    outputs: &[Message],
) -> Message {
    let mut g = Message::new();
    for n in nodes {
        g.message(1, n);
    }
    g.string(2, name);
    for t in initializers {
        g.message(5, t);
    }
    g.string(10, doc);
    for i in inputs {
        g.message(11, i);
    }
    for o in outputs {
        g.message(12, o);
    }
    g
}

/// `ModelProto` (ir_version = 1, producer_name = 2, producer_version = 3,
/// doc_string = 6, graph = 7, opset_import = 8, metadata_props = 14) importing the
/// default domain at `opset` (`OperatorSetIdProto`: domain = 1, version = 2);
/// `metadata` as `StringStringEntryProto` (key = 1, value = 2).
pub fn model(
    ir_version: i64,
    opset: i64,
    producer: (&str, &str),
    doc: &str,
    graph: &Message,
    metadata: &[(String, String)],
) -> Message {
    let mut opset_id = Message::new();
    opset_id.string(1, "").int(2, opset);
    let mut m = Message::new();
    m.int(1, ir_version)
        .string(2, producer.0)
        .string(3, producer.1)
        .string(6, doc)
        .message(7, graph)
        .message(8, &opset_id);
    for (k, v) in metadata {
        let mut e = Message::new();
        e.string(1, k).string(2, v);
        m.message(14, &e);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes(m: &Message) -> Vec<u8> {
        m.clone().into_bytes()
    }

    /// Varints worked out by hand: 7 bits a byte, least significant first, the high
    /// bit set on every byte but the last; a negative int64 takes ten bytes.
    #[test]
    fn varints_by_hand() {
        let mut m = Message::new();
        m.int(1, 1); // key (1 << 3) | 0 = 0x08, value 0x01
        assert_eq!(bytes(&m), [0x08, 0x01]);
        let mut m = Message::new();
        m.int(2, 300); // key 0x10; 300 = 0b10_0101100 -> 0xac 0x02
        assert_eq!(bytes(&m), [0x10, 0xac, 0x02]);
        let mut m = Message::new();
        m.int(3, -1); // key 0x18; 2^64 - 1: nine 0xff then 0x01
        let mut want = vec![0x18];
        want.extend([0xff; 9]);
        want.push(0x01);
        assert_eq!(bytes(&m), want);
        // Field 20 needs a two-byte key: (20 << 3) | 0 = 160 -> 0xa0 0x01.
        let mut m = Message::new();
        m.int(20, 7);
        assert_eq!(bytes(&m), [0xa0, 0x01, 0x07]);
    }

    /// Length-delimited fields and a float: key, length, bytes; fixed32 little-endian.
    #[test]
    fn length_delimited_and_float_by_hand() {
        let mut m = Message::new();
        m.string(4, "Relu"); // key (4 << 3) | 2 = 0x22, length 4
        assert_eq!(bytes(&m), [0x22, 0x04, b'R', b'e', b'l', b'u']);
        let mut m = Message::new();
        m.float(2, 0.1); // key (2 << 3) | 5 = 0x15; 0.1f32 = 0x3dcccccd
        assert_eq!(bytes(&m), [0x15, 0xcd, 0xcc, 0xcc, 0x3d]);
        let mut inner = Message::new();
        inner.int(1, 5);
        let mut m = Message::new();
        m.message(7, &inner); // key 0x3a, length 2, then the inner 0x08 0x05
        assert_eq!(bytes(&m), [0x3a, 0x02, 0x08, 0x05]);
        // A body of 200 bytes has a two-byte length (200 = 0xc8 0x01).
        let mut m = Message::new();
        m.bytes(9, &[0u8; 200]);
        assert_eq!(&bytes(&m)[..3], [0x4a, 0xc8, 0x01]);
        assert_eq!(bytes(&m).len(), 203);
    }

    /// A tensor: dims one key each, data type, name, raw little-endian data.
    #[test]
    fn tensor_with_raw_data_by_hand() {
        let t = tensor_f32("w", &[2, 1], &[1.0, -2.0]);
        let want = [
            0x08, 0x02, // dims = 2
            0x08, 0x01, // dims = 1
            0x10, 0x01, // data_type = FLOAT
            0x42, 0x01, b'w', // name
            0x4a, 0x08, // raw_data, 8 bytes
            0x00, 0x00, 0x80, 0x3f, // 1.0f32 = 0x3f800000
            0x00, 0x00, 0x00, 0xc0, // -2.0f32 = 0xc0000000
        ];
        assert_eq!(bytes(&t), want);
        let t = tensor_i64("i", &[1], &[-2]);
        let mut want = vec![0x08, 0x01, 0x10, 0x07, 0x42, 0x01, b'i', 0x4a, 0x08, 0xfe];
        want.extend([0xff; 7]);
        assert_eq!(bytes(&t), want);
    }

    /// An INTS attribute: name, each value under field 8, then type = 7 under field 20.
    #[test]
    fn ints_attribute_by_hand() {
        let a = attribute("axes", &Attr::Ints(vec![0, 2]));
        let want = [
            0x0a, 0x04, b'a', b'x', b'e', b's', // name
            0x40, 0x00, // ints = 0
            0x40, 0x02, // ints = 2
            0xa0, 0x01, 0x07, // type = INTS
        ];
        assert_eq!(bytes(&a), want);
    }

    /// A value's type with a symbolic batch dimension and a fixed one.
    #[test]
    fn value_info_by_hand() {
        let v = value_info("x", FLOAT, &[Dim::Named("b".into()), Dim::Fixed(3)], "");
        let dim_b = [0x12, 0x01, b'b']; // Dimension.dim_param = "b"
        let dim_3 = [0x08, 0x03]; // Dimension.dim_value = 3
        let mut shape = vec![0x0a, dim_b.len() as u8];
        shape.extend(dim_b);
        shape.extend([0x0a, dim_3.len() as u8]);
        shape.extend(dim_3);
        let mut tensor = vec![0x08, 0x01, 0x12, shape.len() as u8];
        tensor.extend(&shape);
        let mut ty = vec![0x0a, tensor.len() as u8];
        ty.extend(&tensor);
        let mut want = vec![0x0a, 0x01, b'x', 0x12, ty.len() as u8];
        want.extend(&ty);
        assert_eq!(bytes(&v), want);
    }
}
