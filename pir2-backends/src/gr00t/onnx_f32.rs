//! bfloat16 → float32 rewriting of an ONNX file, in Rust, on the protobuf wire format.
//!
//! One file on purpose: the rewriter is one walk down ONNX's message types (model, graph,
//! node, attribute, tensor, type), one function per message, each copying the fields it does
//! not rewrite; the walk is read against `onnx.proto` as a whole, and the external-data
//! writer it feeds is the one place the offsets are chosen.
//!
//! GR00T N1.7's exporter writes the LLM graph in bfloat16 (`llm_bf16.onnx`), and ONNX
//! Runtime's CPU provider has no bfloat16 kernel for most of the ops such a graph uses
//! (`docs/gr00t-contract.md`, "Precision"). [`convert_bf16_to_f32`] writes a float32 copy that
//! the CPU provider runs:
//!
//! - every `TensorProto` of element type BFLOAT16 (16) — graph initializers, sparse
//!   initializers' values, tensors in node attributes (`Constant`, `ConstantOfShape`, …),
//!   in subgraphs and in model-local functions — becomes FLOAT (1), its values widened exactly
//!   (a bfloat16 is the upper half of a float32); the values may be in `raw_data` or in
//!   `int32_data`, inline or in external data;
//! - every node attribute named `to` or `dtype` of value 16 (`Cast`, `RandomNormal`,
//!   `EyeLike`, …) becomes 1;
//! - every tensor type of element type 16 (graph inputs, outputs, `value_info`, nested in
//!   sequence, optional and map types, attribute type protos) becomes 1.
//!
//! Every other byte of the file is copied as it is: the rewriter walks only the messages that
//! can hold one of the above (`ModelProto.graph`, `.functions`, `.training_info` is refused,
//! `GraphProto.{node, initializer, sparse_initializer, input, output, value_info}`,
//! `NodeProto.attribute`, `AttributeProto.{t, g, tensors, graphs, sparse_tensor(s), tp,
//! type_protos}`, `FunctionProto.{node, value_info}`), and copies every other field verbatim,
//! so unknown and future fields survive. Field numbers are those of `onnx/onnx.proto` (ONNX
//! 1.14+).
//!
//! **Size.** A float32 copy of a bfloat16 graph is twice the size of its weights; GR00T
//! N1.7's LLM graph (a 2048-wide Qwen3-VL text model) is past protobuf's 2 GiB in float32. So
//! every converted tensor of at least [`EXTERNAL_MIN_BYTES`], and every tensor that was in
//! external data in the input, is written to `<output file name>.data` beside the output in
//! ONNX's external-data layout (4 KiB-aligned offsets); ONNX Runtime reads it next to the
//! `.onnx` file, so keep the two together. Smaller tensors stay inside the protobuf.
//!
//! **Refused** (one [`Error::OnnxRewrite`] naming the file and the message or tensor): a
//! file that is not a protobuf `ModelProto`, a tensor stored in segments, external data whose
//! file is missing or too short, a bfloat16 tensor whose value count does not match its
//! dims, protobuf groups (wire types 3/4), and `ModelProto.training_info` (training graphs).
//!
//! Numerically, the float32 graph computes what the bfloat16 graph computes with every
//! intermediate kept in float32 instead of being rounded to bfloat16 after each op (a `Cast`
//! to bfloat16 becomes a float32 identity), i.e. at least as precisely.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// ONNX `TensorProto.DataType.FLOAT`.
pub const FLOAT: u64 = 1;
/// ONNX `TensorProto.DataType.BFLOAT16`.
pub const BFLOAT16: u64 = 16;

/// Converted (or previously external) tensors at least this large go to the external-data
/// file.
pub const EXTERNAL_MIN_BYTES: usize = 1024;

/// Alignment of tensors in the external-data file.
const ALIGN: u64 = 4096;

/// What [`convert_bf16_to_f32`] changed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Bf16Report {
    /// bfloat16 tensors (initializers, attribute tensors) widened to float32.
    pub tensors: usize,
    /// Their float32 bytes.
    pub tensor_bytes: u64,
    /// `to` / `dtype` attributes of value 16 set to 1.
    pub attributes: usize,
    /// Tensor types (inputs, outputs, value infos) of element type 16 set to 1.
    pub types: usize,
    /// Tensors written to the external-data file.
    pub external: usize,
    /// The external-data file, when one was written.
    pub data_file: Option<PathBuf>,
}

impl Bf16Report {
    /// Whether the input had anything in bfloat16.
    pub fn changed(&self) -> bool {
        self.tensors + self.attributes + self.types > 0
    }
}

// ---- wire format ----

#[derive(Debug, Clone, Copy)]
enum Wire<'a> {
    Varint(u64),
    I64(&'a [u8]),
    Len(&'a [u8]),
    I32(&'a [u8]),
}

struct Field<'a> {
    num: u32,
    wire: Wire<'a>,
}

fn get_varint(buf: &[u8], pos: &mut usize) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let b = *buf.get(*pos)?;
        *pos += 1;
        v |= u64::from(b & 0x7f) << shift;
        if b & 0x80 == 0 {
            return Some(v);
        }
    }
    None
}

/// Split one message into its fields (in file order).
fn fields(buf: &[u8]) -> std::result::Result<Vec<Field<'_>>, String> {
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < buf.len() {
        let key = get_varint(buf, &mut pos).ok_or("truncated field key")?;
        let num = (key >> 3) as u32;
        let take = |pos: &mut usize, n: usize| -> std::result::Result<&[u8], String> {
            let end = pos.checked_add(n).filter(|&e| e <= buf.len());
            let end = end.ok_or_else(|| format!("field {num} runs past the message"))?;
            let s = &buf[*pos..end];
            *pos = end;
            Ok(s)
        };
        let wire = match key & 7 {
            0 => Wire::Varint(get_varint(buf, &mut pos).ok_or("truncated varint")?),
            1 => Wire::I64(take(&mut pos, 8)?),
            2 => {
                let n = get_varint(buf, &mut pos).ok_or("truncated length")? as usize;
                Wire::Len(take(&mut pos, n)?)
            }
            5 => Wire::I32(take(&mut pos, 4)?),
            w => return Err(format!("field {num} has wire type {w} (protobuf groups)")),
        };
        out.push(Field { num, wire });
    }
    Ok(out)
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn put_field(out: &mut Vec<u8>, num: u32, wire: Wire<'_>) {
    let key = |t: u64| (u64::from(num) << 3) | t;
    match wire {
        Wire::Varint(v) => {
            put_varint(out, key(0));
            put_varint(out, v);
        }
        Wire::I64(b) => {
            put_varint(out, key(1));
            out.extend_from_slice(b);
        }
        Wire::Len(b) => {
            put_varint(out, key(2));
            put_varint(out, b.len() as u64);
            out.extend_from_slice(b);
        }
        Wire::I32(b) => {
            put_varint(out, key(5));
            out.extend_from_slice(b);
        }
    }
}

fn put_len(out: &mut Vec<u8>, num: u32, bytes: &[u8]) {
    put_field(out, num, Wire::Len(bytes));
}

fn as_str(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

// ---- the rewriter ----

struct Rewriter {
    input: PathBuf,
    in_dir: PathBuf,
    data_path: PathBuf,
    data_name: String,
    data: Option<File>,
    offset: u64,
    report: Bf16Report,
    /// Only count what would change (no data read or written).
    dry: bool,
    /// Widen bfloat16 (false: copy, only re-homing external data).
    convert: bool,
}

impl Rewriter {
    fn err(&self, what: impl Into<String>, problem: impl Into<String>) -> Error {
        Error::OnnxRewrite {
            path: self.input.clone(),
            what: what.into(),
            problem: problem.into(),
        }
    }

    fn parse<'a>(&self, buf: &'a [u8], what: &str) -> Result<Vec<Field<'a>>> {
        fields(buf).map_err(|e| self.err(what, format!("not a protobuf message: {e}")))
    }

    /// Append `bytes` to the external-data file; returns its offset.
    fn write_external(&mut self, bytes: &[u8]) -> Result<u64> {
        if self.data.is_none() {
            let f = File::create(&self.data_path).map_err(|source| Error::Read {
                path: self.data_path.clone(),
                source,
            })?;
            self.data = Some(f);
            self.report.data_file = Some(self.data_path.clone());
        }
        let pad = (ALIGN - self.offset % ALIGN) % ALIGN;
        let f = self.data.as_mut().expect("opened above");
        let io = |source| Error::Read {
            path: self.data_path.clone(),
            source,
        };
        f.write_all(&vec![0u8; pad as usize]).map_err(io)?;
        f.write_all(bytes).map_err(io)?;
        let at = self.offset + pad;
        self.offset = at + bytes.len() as u64;
        self.report.external += 1;
        Ok(at)
    }

    fn model(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "ModelProto")? {
            match (f.num, f.wire) {
                (7, Wire::Len(b)) => {
                    let g = self.graph(b)?;
                    put_len(&mut out, 7, &g);
                }
                (25, Wire::Len(b)) => {
                    let g = self.function(b)?;
                    put_len(&mut out, 25, &g);
                }
                (20, _) => {
                    return Err(self.err(
                        "ModelProto.training_info",
                        "training graphs are not rewritten; export the model for inference",
                    ))
                }
                (n, w) => put_field(&mut out, n, w),
            }
        }
        Ok(out)
    }

    fn graph(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "GraphProto")? {
            let rewritten = match (f.num, f.wire) {
                (1, Wire::Len(b)) => Some(self.node(b)?),
                (5, Wire::Len(b)) => Some(self.tensor(b, "initializer")?),
                (11..=13, Wire::Len(b)) => Some(self.value_info(b)?),
                (15, Wire::Len(b)) => Some(self.sparse(b)?),
                _ => None,
            };
            match rewritten {
                Some(m) => put_len(&mut out, f.num, &m),
                None => put_field(&mut out, f.num, f.wire),
            }
        }
        Ok(out)
    }

    fn function(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "FunctionProto")? {
            let rewritten = match (f.num, f.wire) {
                (7, Wire::Len(b)) => Some(self.node(b)?),
                (12, Wire::Len(b)) => Some(self.value_info(b)?),
                _ => None,
            };
            match rewritten {
                Some(m) => put_len(&mut out, f.num, &m),
                None => put_field(&mut out, f.num, f.wire),
            }
        }
        Ok(out)
    }

    fn node(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "NodeProto")? {
            match (f.num, f.wire) {
                (5, Wire::Len(b)) => {
                    let a = self.attribute(b)?;
                    put_len(&mut out, 5, &a);
                }
                (n, w) => put_field(&mut out, n, w),
            }
        }
        Ok(out)
    }

    fn attribute(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let fs = self.parse(buf, "AttributeProto")?;
        let name = fs
            .iter()
            .find_map(|f| match (f.num, f.wire) {
                (1, Wire::Len(b)) => Some(as_str(b)),
                _ => None,
            })
            .unwrap_or_default();
        let what = format!("attribute `{name}`");
        let mut out = Vec::with_capacity(buf.len());
        for f in fs {
            let rewritten = match (f.num, f.wire) {
                (3, Wire::Varint(BFLOAT16))
                    if self.convert && (name == "to" || name == "dtype") =>
                {
                    self.report.attributes += 1;
                    put_field(&mut out, 3, Wire::Varint(FLOAT));
                    continue;
                }
                (5 | 10, Wire::Len(b)) => Some(self.tensor(b, &what)?),
                (6 | 11, Wire::Len(b)) => Some(self.graph(b)?),
                (22 | 23, Wire::Len(b)) => Some(self.sparse(b)?),
                (14 | 15, Wire::Len(b)) => Some(self.type_proto(b)?),
                _ => None,
            };
            match rewritten {
                Some(m) => put_len(&mut out, f.num, &m),
                None => put_field(&mut out, f.num, f.wire),
            }
        }
        Ok(out)
    }

    fn sparse(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "SparseTensorProto")? {
            match (f.num, f.wire) {
                (1, Wire::Len(b)) => {
                    let t = self.tensor(b, "sparse values")?;
                    put_len(&mut out, 1, &t);
                }
                (2, Wire::Len(b)) => {
                    let t = self.tensor(b, "sparse indices")?;
                    put_len(&mut out, 2, &t);
                }
                (n, w) => put_field(&mut out, n, w),
            }
        }
        Ok(out)
    }

    fn value_info(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "ValueInfoProto")? {
            match (f.num, f.wire) {
                (2, Wire::Len(b)) => {
                    let t = self.type_proto(b)?;
                    put_len(&mut out, 2, &t);
                }
                (n, w) => put_field(&mut out, n, w),
            }
        }
        Ok(out)
    }

    /// `TypeProto`: `tensor_type` (1) and `sparse_tensor_type` (8) carry `elem_type` (1);
    /// `sequence_type` (4) and `optional_type` (9) nest a `TypeProto` at 1, `map_type` (5)
    /// at 2.
    fn type_proto(&mut self, buf: &[u8]) -> Result<Vec<u8>> {
        let mut out = Vec::with_capacity(buf.len());
        for f in self.parse(buf, "TypeProto")? {
            match (f.num, f.wire) {
                (1 | 8, Wire::Len(b)) => {
                    let mut inner = Vec::with_capacity(b.len());
                    for g in self.parse(b, "TypeProto.Tensor")? {
                        match (g.num, g.wire) {
                            (1, Wire::Varint(BFLOAT16)) if self.convert => {
                                self.report.types += 1;
                                put_field(&mut inner, 1, Wire::Varint(FLOAT));
                            }
                            (n, w) => put_field(&mut inner, n, w),
                        }
                    }
                    put_len(&mut out, f.num, &inner);
                }
                (4 | 9 | 5, Wire::Len(b)) => {
                    let nested = if f.num == 5 { 2 } else { 1 };
                    let mut inner = Vec::with_capacity(b.len());
                    for g in self.parse(b, "TypeProto (nested)")? {
                        match (g.num, g.wire) {
                            (n, Wire::Len(t)) if n == nested => {
                                let t = self.type_proto(t)?;
                                put_len(&mut inner, n, &t);
                            }
                            (n, w) => put_field(&mut inner, n, w),
                        }
                    }
                    put_len(&mut out, f.num, &inner);
                }
                (n, w) => put_field(&mut out, n, w),
            }
        }
        Ok(out)
    }

    /// Read the bytes of an external tensor (`location`, `offset`, `length` relative to the
    /// input file's directory).
    fn read_external(&self, what: &str, entries: &[(String, String)]) -> Result<Vec<u8>> {
        let get = |k: &str| entries.iter().find(|(key, _)| key == k).map(|(_, v)| v);
        let location =
            get("location").ok_or_else(|| self.err(what, "external data without a `location`"))?;
        let num = |k: &str| -> Result<Option<u64>> {
            get(k)
                .map(|v| {
                    v.parse::<u64>().map_err(|_| {
                        self.err(what, format!("external data `{k}` = `{v}` is not a number"))
                    })
                })
                .transpose()
        };
        let offset = num("offset")?.unwrap_or(0);
        let path = self.in_dir.join(location);
        let mut f = File::open(&path).map_err(|e| {
            self.err(
                what,
                format!(
                    "its external data `{}` cannot be read ({e}); keep the `.data` file next to the `.onnx` file",
                    path.display()
                ),
            )
        })?;
        let len = f.metadata().map(|m| m.len()).unwrap_or(0);
        let length = match num("length")? {
            Some(l) => l,
            None => len.saturating_sub(offset),
        };
        if offset.checked_add(length).is_none_or(|e| e > len) {
            return Err(self.err(
                what,
                format!(
                    "external data `{}` bytes {offset}..{} are past its end ({len} bytes)",
                    path.display(),
                    offset.saturating_add(length)
                ),
            ));
        }
        f.seek(SeekFrom::Start(offset))
            .map_err(|e| self.err(what, e.to_string()))?;
        let mut bytes = vec![0u8; length as usize];
        f.read_exact(&mut bytes)
            .map_err(|e| self.err(what, e.to_string()))?;
        Ok(bytes)
    }

    /// `TensorProto`: dims 1, data_type 2, segment 3, int32_data 5, name 8, raw_data 9,
    /// external_data 13 (`StringStringEntryProto` key 1, value 2), data_location 14.
    fn tensor(&mut self, buf: &[u8], role: &str) -> Result<Vec<u8>> {
        let fs = self.parse(buf, "TensorProto")?;
        let mut data_type = 0u64;
        let mut name = String::new();
        let mut external = false;
        let mut dims: Vec<u64> = Vec::new();
        let mut entries = Vec::new();
        for f in &fs {
            match (f.num, f.wire) {
                (1, Wire::Varint(d)) => dims.push(d),
                (1, Wire::Len(b)) => {
                    let mut p = 0;
                    while p < b.len() {
                        dims.push(get_varint(b, &mut p).unwrap_or(0));
                    }
                }
                (2, Wire::Varint(t)) => data_type = t,
                (8, Wire::Len(b)) => name = as_str(b),
                (14, Wire::Varint(1)) => external = true,
                (13, Wire::Len(b)) => {
                    let (mut k, mut v) = (String::new(), String::new());
                    for e in self.parse(b, "StringStringEntryProto")? {
                        match (e.num, e.wire) {
                            (1, Wire::Len(s)) => k = as_str(s),
                            (2, Wire::Len(s)) => v = as_str(s),
                            _ => {}
                        }
                    }
                    entries.push((k, v));
                }
                (3, _) => {
                    return Err(self.err(
                        format!("{role} `{name}`"),
                        "tensors stored in segments are not supported",
                    ))
                }
                _ => {}
            }
        }
        let what = format!("{role} `{name}`");
        if self.dry {
            self.report.tensors += usize::from(data_type == BFLOAT16);
            return Ok(Vec::new());
        }
        let bf16 = self.convert && data_type == BFLOAT16;
        if !bf16 && !external {
            return Ok(buf.to_vec());
        }
        // The tensor's bytes, as float32 when it was bfloat16.
        let bytes = if external {
            let raw = self.read_external(&what, &entries)?;
            if bf16 {
                widen(&raw)
            } else {
                raw
            }
        } else {
            let mut halves: Vec<u16> = Vec::new();
            let mut raw: Option<&[u8]> = None;
            for f in &fs {
                match (f.num, f.wire) {
                    (9, Wire::Len(b)) => raw = Some(b),
                    // int32_data holds one bfloat16 bit pattern per element (low 16 bits).
                    (5, Wire::Varint(v)) => halves.push(v as u16),
                    (5, Wire::Len(b)) => {
                        let mut p = 0;
                        while p < b.len() {
                            let v = get_varint(b, &mut p)
                                .ok_or_else(|| self.err(&what, "truncated int32_data"))?;
                            halves.push(v as u16);
                        }
                    }
                    _ => {}
                }
            }
            match raw {
                Some(r) => widen(r),
                None => halves
                    .iter()
                    .flat_map(|&h| (u32::from(h) << 16).to_le_bytes())
                    .collect(),
            }
        };
        let count: u64 = dims.iter().product();
        let width = if bf16 {
            Some(4)
        } else {
            element_width(data_type)
        };
        if let Some(w) = width {
            if count * w != bytes.len() as u64 {
                return Err(self.err(
                    &what,
                    format!(
                        "dims {dims:?} hold {count} values but the data has {} bytes ({} per value)",
                        bytes.len(),
                        w
                    ),
                ));
            }
        }
        if bf16 {
            self.report.tensors += 1;
            self.report.tensor_bytes += bytes.len() as u64;
        }
        // Re-emit: every field but the type and the data, then the new type and data.
        let mut out = Vec::with_capacity(bytes.len() + 64);
        for f in &fs {
            match f.num {
                2 | 4 | 5 | 9 | 13 | 14 => {}
                n => put_field(&mut out, n, f.wire),
            }
        }
        put_field(
            &mut out,
            2,
            Wire::Varint(if bf16 { FLOAT } else { data_type }),
        );
        if external || bytes.len() >= EXTERNAL_MIN_BYTES {
            let at = self.write_external(&bytes)?;
            let entry = |k: &str, v: &str| {
                let mut e = Vec::new();
                put_len(&mut e, 1, k.as_bytes());
                put_len(&mut e, 2, v.as_bytes());
                e
            };
            let location = self.data_name.clone();
            put_len(&mut out, 13, &entry("location", &location));
            put_len(&mut out, 13, &entry("offset", &at.to_string()));
            put_len(&mut out, 13, &entry("length", &bytes.len().to_string()));
            put_field(&mut out, 14, Wire::Varint(1));
        } else {
            put_len(&mut out, 9, &bytes);
        }
        Ok(out)
    }
}

/// Bytes per value of the fixed-width ONNX element types (`None`: strings and the rest).
fn element_width(t: u64) -> Option<u64> {
    Some(match t {
        1 | 6 | 12 => 4,       // float, int32, uint32
        2 | 3 | 9 => 1,        // uint8, int8, bool
        4 | 5 | 10 | 16 => 2,  // uint16, int16, float16, bfloat16
        7 | 11 | 13 | 14 => 8, // int64, double, uint64, complex64
        15 => 16,              // complex128
        _ => return None,
    })
}

/// bfloat16 little-endian bytes → float32 little-endian bytes (exact).
fn widen(raw: &[u8]) -> Vec<u8> {
    raw.chunks_exact(2)
        .flat_map(|b| (u32::from(u16::from_le_bytes([b[0], b[1]])) << 16).to_le_bytes())
        .collect()
}

/// Write a float32 copy of the ONNX file `input` to `output` (see the module docs), and
/// its large tensors to `<output file name>.data` beside it. `output` and its `.data` file
/// must not exist (nothing a user wrote is overwritten); on an error they are removed.
pub fn convert_bf16_to_f32(input: &Path, output: &Path) -> Result<Bf16Report> {
    rewrite(input, output, true)
}

/// Copy the ONNX file `input` to `output` unchanged but for its external data, which is
/// gathered into `<output file name>.data` (so the copy does not depend on files next to the
/// input). bfloat16 stays bfloat16.
pub fn copy_onnx(input: &Path, output: &Path) -> Result<Bf16Report> {
    rewrite(input, output, false)
}

fn rewrite(input: &Path, output: &Path, convert: bool) -> Result<Bf16Report> {
    let name = output
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| Error::OnnxRewrite {
            path: output.to_path_buf(),
            what: "output".into(),
            problem: "has no file name".into(),
        })?;
    let data_name = format!("{name}.data");
    let data_path = output.with_file_name(&data_name);
    for p in [output, data_path.as_path()] {
        if p.exists() {
            return Err(Error::OnnxRewrite {
                path: p.to_path_buf(),
                what: "output".into(),
                problem: "already exists; nothing was overwritten".into(),
            });
        }
    }
    let bytes = std::fs::read(input).map_err(|source| Error::Read {
        path: input.to_path_buf(),
        source,
    })?;
    let mut rw = Rewriter {
        input: input.to_path_buf(),
        in_dir: input.parent().unwrap_or(Path::new(".")).to_path_buf(),
        data_path: data_path.clone(),
        data_name,
        data: None,
        offset: 0,
        report: Bf16Report::default(),
        dry: false,
        convert,
    };
    let result = (|| -> Result<Vec<u8>> {
        let out = rw.model(&bytes)?;
        if out.len() > (1usize << 31) - 1 {
            return Err(rw.err(
                "ModelProto",
                format!("the rewritten protobuf is {} bytes, past 2 GiB", out.len()),
            ));
        }
        Ok(out)
    })();
    let out = match result {
        Ok(o) => o,
        Err(e) => {
            drop(rw.data.take());
            let _ = std::fs::remove_file(&data_path);
            return Err(e);
        }
    };
    if let Some(f) = rw.data.take() {
        f.sync_all().map_err(|source| Error::Read {
            path: data_path.clone(),
            source,
        })?;
    }
    std::fs::write(output, out).map_err(|source| Error::Read {
        path: output.to_path_buf(),
        source,
    })?;
    Ok(rw.report)
}

/// Whether the ONNX file `path` declares any bfloat16 tensor, type or `to`/`dtype` attribute
/// (the same walk as [`convert_bf16_to_f32`], nothing written).
pub fn has_bf16(path: &Path) -> Result<bool> {
    let bytes = std::fs::read(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let mut rw = Rewriter {
        input: path.to_path_buf(),
        in_dir: PathBuf::new(),
        data_path: PathBuf::new(),
        data_name: String::new(),
        data: None,
        offset: 0,
        report: Bf16Report::default(),
        dry: true,
        convert: true,
    };
    rw.model(&bytes)?;
    Ok(rw.report.changed())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varints_round_trip() {
        for v in [0u64, 1, 127, 128, 300, u32::MAX as u64, u64::MAX] {
            let mut b = Vec::new();
            put_varint(&mut b, v);
            let mut p = 0;
            assert_eq!(get_varint(&b, &mut p), Some(v));
            assert_eq!(p, b.len());
        }
    }

    #[test]
    fn widening_is_exact() {
        let x = [1.0f32, -2.5, 3.140625, 0.0];
        let raw: Vec<u8> = x
            .iter()
            .flat_map(|v| ((v.to_bits() >> 16) as u16).to_le_bytes())
            .collect();
        let w = widen(&raw);
        let back: Vec<f32> = w
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(back, x);
    }

    #[test]
    fn groups_are_refused() {
        // field 1, wire type 3 (start group)
        assert!(fields(&[0x0b]).is_err());
    }
}
