//! A minimal protobuf (proto3 wire format) encoder for the subset of `onnx.proto` that an
//! exporter needs: `ModelProto`, `OperatorSetIdProto`, `GraphProto`, `NodeProto`,
//! `AttributeProto`, `TensorProto`, `ValueInfoProto` and the tensor `TypeProto`.
//!
//! Field numbers follow `onnx/onnx.proto` (ONNX 1.14+). Only encoding is implemented; no
//! `protoc`, no generated code. Every message is encoded by `encode(&self, &mut Vec<u8>)`
//! and nested as a length-delimited field.

/// Protobuf wire types.
const WIRE_VARINT: u32 = 0;
const WIRE_I64: u32 = 1;
const WIRE_LEN: u32 = 2;
const WIRE_I32: u32 = 5;

fn put_varint(buf: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        buf.push((v as u8) | 0x80);
        v >>= 7;
    }
    buf.push(v as u8);
}

fn put_key(buf: &mut Vec<u8>, field: u32, wire: u32) {
    put_varint(buf, u64::from((field << 3) | wire));
}

fn put_int(buf: &mut Vec<u8>, field: u32, v: i64) {
    put_key(buf, field, WIRE_VARINT);
    // Negative int64/int32 values are encoded as 10-byte two's complement varints.
    put_varint(buf, v as u64);
}

fn put_bytes(buf: &mut Vec<u8>, field: u32, bytes: &[u8]) {
    put_key(buf, field, WIRE_LEN);
    put_varint(buf, bytes.len() as u64);
    buf.extend_from_slice(bytes);
}

fn put_str(buf: &mut Vec<u8>, field: u32, s: &str) {
    if !s.is_empty() {
        put_bytes(buf, field, s.as_bytes());
    }
}

fn put_f32(buf: &mut Vec<u8>, field: u32, v: f32) {
    put_key(buf, field, WIRE_I32);
    buf.extend_from_slice(&v.to_le_bytes());
}

fn put_msg(buf: &mut Vec<u8>, field: u32, encode: impl FnOnce(&mut Vec<u8>)) {
    let mut inner = Vec::new();
    encode(&mut inner);
    put_bytes(buf, field, &inner);
}

fn put_packed_i64(buf: &mut Vec<u8>, field: u32, vs: &[i64]) {
    if vs.is_empty() {
        return;
    }
    let mut inner = Vec::with_capacity(vs.len() * 2);
    for &v in vs {
        put_varint(&mut inner, v as u64);
    }
    put_bytes(buf, field, &inner);
}

fn put_packed_f32(buf: &mut Vec<u8>, field: u32, vs: &[f32]) {
    if vs.is_empty() {
        return;
    }
    let mut inner = Vec::with_capacity(vs.len() * 4);
    for &v in vs {
        inner.extend_from_slice(&v.to_le_bytes());
    }
    put_bytes(buf, field, &inner);
}

#[allow(dead_code)]
fn put_f64(buf: &mut Vec<u8>, field: u32, v: f64) {
    put_key(buf, field, WIRE_I64);
    buf.extend_from_slice(&v.to_le_bytes());
}

/// `TensorProto.DataType` values used here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(i32)]
pub enum DataType {
    /// 32-bit float.
    Float = 1,
    /// 64-bit signed integer.
    Int64 = 7,
    /// Boolean (graph inputs only; no initializer of this type is written).
    Bool = 9,
}

/// A constant tensor (`TensorProto`), stored little-endian in `raw_data`.
#[derive(Debug, Clone, PartialEq)]
pub struct TensorProto {
    /// Tensor name (initializer names are graph-global).
    pub name: String,
    /// Dimensions, outermost first.
    pub dims: Vec<i64>,
    /// Element type.
    pub data_type: DataType,
    /// Little-endian element bytes (empty when [`Self::external`] is set).
    pub raw_data: Vec<u8>,
    /// ONNX external data: the bytes live in the file `location` (relative to the model
    /// file) at `offset`, `length` bytes long, instead of in `raw_data`.
    pub external: Option<ExternalData>,
}

/// Where a tensor's bytes live outside the protobuf (ONNX `external_data`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExternalData {
    /// File name relative to the model file.
    pub location: String,
    /// Byte offset in that file.
    pub offset: u64,
    /// Byte length.
    pub length: u64,
}

impl TensorProto {
    /// An `f32` tensor.
    pub fn f32(name: impl Into<String>, dims: &[usize], data: &[f32]) -> Self {
        debug_assert_eq!(dims.iter().product::<usize>(), data.len());
        let mut raw = Vec::with_capacity(data.len() * 4);
        for v in data {
            raw.extend_from_slice(&v.to_le_bytes());
        }
        TensorProto {
            name: name.into(),
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: DataType::Float,
            raw_data: raw,
            external: None,
        }
    }

    /// An `i64` tensor.
    pub fn i64(name: impl Into<String>, dims: &[usize], data: &[i64]) -> Self {
        debug_assert_eq!(dims.iter().product::<usize>(), data.len());
        let mut raw = Vec::with_capacity(data.len() * 8);
        for v in data {
            raw.extend_from_slice(&v.to_le_bytes());
        }
        TensorProto {
            name: name.into(),
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: DataType::Int64,
            raw_data: raw,
            external: None,
        }
    }

    fn encode(&self, buf: &mut Vec<u8>) {
        put_packed_i64(buf, 1, &self.dims);
        put_int(buf, 2, self.data_type as i64);
        put_str(buf, 8, &self.name);
        match &self.external {
            None => {
                // raw_data must be present even for empty tensors so the type is unambiguous.
                put_bytes(buf, 9, &self.raw_data);
            }
            Some(e) => {
                // external_data (13): StringStringEntryProto {key = 1, value = 2};
                // data_location (14): EXTERNAL = 1.
                for (k, v) in [
                    ("location", e.location.clone()),
                    ("offset", e.offset.to_string()),
                    ("length", e.length.to_string()),
                ] {
                    put_msg(buf, 13, |b| {
                        put_str(b, 1, k);
                        put_str(b, 2, &v);
                    });
                }
                put_int(buf, 14, 1);
            }
        }
    }
}

/// A node attribute (`AttributeProto`).
#[derive(Debug, Clone, PartialEq)]
pub enum AttrValue {
    /// `FLOAT`.
    Float(f32),
    /// `INT`.
    Int(i64),
    /// `STRING`.
    Str(String),
    /// `TENSOR`.
    Tensor(TensorProto),
    /// `FLOATS`.
    Floats(Vec<f32>),
    /// `INTS`.
    Ints(Vec<i64>),
}

/// A named attribute.
#[derive(Debug, Clone, PartialEq)]
pub struct Attribute {
    /// Attribute name.
    pub name: String,
    /// Its value.
    pub value: AttrValue,
}

impl Attribute {
    fn encode(&self, buf: &mut Vec<u8>) {
        put_str(buf, 1, &self.name);
        // AttributeProto.AttributeType: FLOAT=1, INT=2, STRING=3, TENSOR=4, FLOATS=6, INTS=7.
        match &self.value {
            AttrValue::Float(f) => {
                put_f32(buf, 2, *f);
                put_int(buf, 20, 1);
            }
            AttrValue::Int(i) => {
                put_int(buf, 3, *i);
                put_int(buf, 20, 2);
            }
            AttrValue::Str(s) => {
                put_bytes(buf, 4, s.as_bytes());
                put_int(buf, 20, 3);
            }
            AttrValue::Tensor(t) => {
                put_msg(buf, 5, |b| t.encode(b));
                put_int(buf, 20, 4);
            }
            AttrValue::Floats(fs) => {
                put_packed_f32(buf, 7, fs);
                put_int(buf, 20, 6);
            }
            AttrValue::Ints(is) => {
                put_packed_i64(buf, 8, is);
                put_int(buf, 20, 7);
            }
        }
    }
}

/// One operator application (`NodeProto`).
#[derive(Debug, Clone, PartialEq)]
pub struct NodeProto {
    /// Operator type, e.g. `"Gemm"`.
    pub op_type: String,
    /// Node name (unique in the graph).
    pub name: String,
    /// Input value names (`""` = omitted optional input).
    pub inputs: Vec<String>,
    /// Output value names.
    pub outputs: Vec<String>,
    /// Attributes.
    pub attributes: Vec<Attribute>,
}

impl NodeProto {
    fn encode(&self, buf: &mut Vec<u8>) {
        for i in &self.inputs {
            put_bytes(buf, 1, i.as_bytes());
        }
        for o in &self.outputs {
            put_bytes(buf, 2, o.as_bytes());
        }
        put_str(buf, 3, &self.name);
        put_str(buf, 4, &self.op_type);
        for a in &self.attributes {
            put_msg(buf, 5, |b| a.encode(b));
        }
    }
}

/// One dimension of a value's declared shape.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Dim {
    /// A fixed size.
    Fixed(usize),
    /// A symbolic (dynamic) size, e.g. `"batch"`.
    Symbolic(String),
}

/// A graph input or output (`ValueInfoProto` with a tensor `TypeProto`).
#[derive(Debug, Clone, PartialEq)]
pub struct ValueInfoProto {
    /// Value name.
    pub name: String,
    /// Element type.
    pub elem_type: DataType,
    /// Declared shape.
    pub shape: Vec<Dim>,
}

impl ValueInfoProto {
    fn encode(&self, buf: &mut Vec<u8>) {
        put_str(buf, 1, &self.name);
        // TypeProto { tensor_type = 1: TypeProto.Tensor { elem_type = 1, shape = 2 } }
        put_msg(buf, 2, |tp| {
            put_msg(tp, 1, |tt| {
                put_int(tt, 1, self.elem_type as i64);
                put_msg(tt, 2, |sh| {
                    for d in &self.shape {
                        put_msg(sh, 1, |dim| match d {
                            Dim::Fixed(n) => put_int(dim, 1, *n as i64),
                            Dim::Symbolic(s) => put_bytes(dim, 2, s.as_bytes()),
                        });
                    }
                });
            });
        });
    }
}

/// A computation graph (`GraphProto`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct GraphProto {
    /// Graph name.
    pub name: String,
    /// Nodes in topological order.
    pub nodes: Vec<NodeProto>,
    /// Constant tensors (weights).
    pub initializers: Vec<TensorProto>,
    /// Graph inputs.
    pub inputs: Vec<ValueInfoProto>,
    /// Graph outputs.
    pub outputs: Vec<ValueInfoProto>,
    /// Free-form documentation.
    pub doc_string: String,
}

impl GraphProto {
    fn encode(&self, buf: &mut Vec<u8>) {
        for n in &self.nodes {
            put_msg(buf, 1, |b| n.encode(b));
        }
        put_str(buf, 2, &self.name);
        for t in &self.initializers {
            put_msg(buf, 5, |b| t.encode(b));
        }
        put_str(buf, 10, &self.doc_string);
        for v in &self.inputs {
            put_msg(buf, 11, |b| v.encode(b));
        }
        for v in &self.outputs {
            put_msg(buf, 12, |b| v.encode(b));
        }
    }
}

/// A whole model (`ModelProto`).
#[derive(Debug, Clone, PartialEq)]
pub struct ModelProto {
    /// IR version (8 goes with opset 17).
    pub ir_version: i64,
    /// Default-domain opset version.
    pub opset: i64,
    /// Producer name.
    pub producer_name: String,
    /// Producer version.
    pub producer_version: String,
    /// The graph.
    pub graph: GraphProto,
    /// `metadata_props` key/value pairs.
    pub metadata: Vec<(String, String)>,
}

impl ModelProto {
    /// Encode to protobuf bytes (the content of a `.onnx` file).
    pub fn encode(&self) -> Vec<u8> {
        let mut buf = Vec::new();
        put_int(&mut buf, 1, self.ir_version);
        put_str(&mut buf, 2, &self.producer_name);
        put_str(&mut buf, 3, &self.producer_version);
        put_msg(&mut buf, 7, |b| self.graph.encode(b));
        put_msg(&mut buf, 8, |b| {
            // OperatorSetIdProto { domain = 1 ("" = ai.onnx), version = 2 }
            put_int(b, 2, self.opset);
        });
        for (k, v) in &self.metadata {
            put_msg(&mut buf, 14, |b| {
                put_str(b, 1, k);
                put_str(b, 2, v);
            });
        }
        buf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varint_matches_protobuf_reference_encodings() {
        let enc = |v: u64| {
            let mut b = Vec::new();
            put_varint(&mut b, v);
            b
        };
        assert_eq!(enc(1), vec![0x01]);
        assert_eq!(enc(150), vec![0x96, 0x01]);
        assert_eq!(enc(300), vec![0xac, 0x02]);
        // -1 as int64: ten bytes, all continuation bits but the last.
        assert_eq!(
            enc(-1i64 as u64),
            vec![0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x01]
        );
    }

    #[test]
    fn tensor_proto_layout_is_dims_type_name_raw() {
        let t = TensorProto::f32("w", &[2], &[1.0, 2.0]);
        let mut b = Vec::new();
        t.encode(&mut b);
        // dims, packed: key (1<<3|2) = 0x0a, length 1, value 2
        assert_eq!(&b[..3], &[0x0a, 0x01, 0x02]);
        // data_type: key 0x10, value 1
        assert_eq!(&b[3..5], &[0x10, 0x01]);
        // name: key 0x42, len 1, 'w'
        assert_eq!(&b[5..8], &[0x42, 0x01, b'w']);
        // raw_data: key 0x4a, len 8, then 1.0f32 LE, 2.0f32 LE
        assert_eq!(&b[8..10], &[0x4a, 0x08]);
        assert_eq!(&b[10..14], &1.0f32.to_le_bytes());
        assert_eq!(&b[14..18], &2.0f32.to_le_bytes());
    }
}
