//! Reading Isaac-GR00T's files: their names, JSON values that carry the file they are in and
//! their JSON path (so every refusal names both, as one [`Error::Import`]), where the
//! processor's files are, and the head loader's errors restated as import errors.

use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use crate::error::{Error, Result};

/// GR00T's model configuration file.
pub const CONFIG_FILE: &str = "config.json";
/// GR00T's processor configuration (`Gr00tN1d7Processor.save_pretrained`).
pub const PROCESSOR_FILE: &str = "processor_config.json";
/// GR00T's normalisation statistics.
pub const STATISTICS_FILE: &str = "statistics.json";
/// GR00T's embodiment slots `{tag: id}`.
pub const EMBODIMENT_ID_FILE: &str = "embodiment_id.json";

pub(super) fn err(path: &Path, field: impl Into<String>, problem: impl Into<String>) -> Error {
    Error::Import {
        path: path.to_path_buf(),
        field: field.into(),
        problem: problem.into(),
    }
}

/// A JSON value with the file it is in and its JSON path, so every error names both.
#[derive(Clone, Copy)]
pub(super) struct Node<'a> {
    pub(super) v: &'a Value,
    pub(super) path: &'a Path,
}

pub(super) struct At<'a> {
    pub(super) node: Node<'a>,
    pub(super) field: String,
}

impl<'a> At<'a> {
    pub(super) fn root(v: &'a Value, path: &'a Path, field: &str) -> Self {
        At {
            node: Node { v, path },
            field: field.to_string(),
        }
    }
    pub(super) fn err(&self, problem: impl Into<String>) -> Error {
        err(self.node.path, &self.field, problem)
    }
    fn sub(&self, key: &str) -> String {
        if self.field.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.field)
        }
    }
    pub(super) fn obj(&self) -> Result<&'a Map<String, Value>> {
        self.node
            .v
            .as_object()
            .ok_or_else(|| self.err(format!("must be an object, got {}", short(self.node.v))))
    }
    /// The value at `key` (absent or null: `None`).
    pub(super) fn opt(&self, key: &str) -> Result<Option<At<'a>>> {
        Ok(match self.obj()?.get(key) {
            None | Some(Value::Null) => None,
            Some(v) => Some(At {
                node: Node {
                    v,
                    path: self.node.path,
                },
                field: self.sub(key),
            }),
        })
    }
    pub(super) fn key(&self, key: &str) -> Result<At<'a>> {
        self.opt(key)?
            .ok_or_else(|| err(self.node.path, self.sub(key), "is missing"))
    }
    pub(super) fn bool(&self) -> Result<bool> {
        self.node
            .v
            .as_bool()
            .ok_or_else(|| self.err(format!("must be true or false, got {}", short(self.node.v))))
    }
    pub(super) fn u64(&self) -> Result<u64> {
        self.node.v.as_u64().ok_or_else(|| {
            self.err(format!(
                "must be a non-negative integer, got {}",
                short(self.node.v)
            ))
        })
    }
    pub(super) fn f64(&self) -> Result<f64> {
        self.node
            .v
            .as_f64()
            .ok_or_else(|| self.err(format!("must be a number, got {}", short(self.node.v))))
    }
    pub(super) fn str(&self) -> Result<&'a str> {
        self.node
            .v
            .as_str()
            .ok_or_else(|| self.err(format!("must be a string, got {}", short(self.node.v))))
    }
    pub(super) fn items(&self) -> Result<Vec<At<'a>>> {
        let a = self
            .node
            .v
            .as_array()
            .ok_or_else(|| self.err(format!("must be a list, got {}", short(self.node.v))))?;
        Ok(a.iter()
            .enumerate()
            .map(|(i, v)| At {
                node: Node {
                    v,
                    path: self.node.path,
                },
                field: format!("{}[{i}]", self.field),
            })
            .collect())
    }
    pub(super) fn strings(&self) -> Result<Vec<String>> {
        self.items()?
            .iter()
            .map(|a| a.str().map(str::to_string))
            .collect()
    }
    pub(super) fn ints(&self) -> Result<Vec<i64>> {
        self.items()?
            .iter()
            .map(|a| {
                a.node
                    .v
                    .as_i64()
                    .ok_or_else(|| a.err(format!("must be an integer, got {}", short(a.node.v))))
            })
            .collect()
    }
    /// Refuse keys outside `known`.
    pub(super) fn only(&self, known: &[&str], whose: &str) -> Result<()> {
        for k in self.obj()?.keys() {
            if !known.contains(&k.as_str()) {
                return Err(err(
                    self.node.path,
                    self.sub(k),
                    format!(
                        "is not a field of {whose} that pir2 knows (known: {}); pir2 does not \
                         guess what it means",
                        known.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }
}

pub(super) fn short(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 60 {
        format!(
            "{}…",
            &s[..s.char_indices().nth(57).map_or(s.len(), |(i, _)| i)]
        )
    } else {
        s
    }
}

pub(super) fn read_json(path: &Path) -> Result<Value> {
    if !path.is_file() {
        return Err(err(
            path,
            path.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            "is missing (Isaac-GR00T writes it next to config.json)",
        ));
    }
    let text = std::fs::read_to_string(path).map_err(|source| Error::Read {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|e| Error::Parse {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// The processor's files are in the checkpoint root; a checkpoint whose processor was saved
/// into `processor/` is read from there.
pub(super) fn processor_file(ckpt: &Path, name: &str) -> PathBuf {
    let root = ckpt.join(name);
    let sub = ckpt.join("processor").join(name);
    if !root.exists() && sub.exists() {
        sub
    } else {
        root
    }
}

/// A crate error of the head loader as one import error naming the file and the tensor or
/// field.
pub(super) fn from_head(e: Error, fallback: &Path) -> Error {
    use Error as E;
    match e {
        E::MissingTensor { path, name } => err(&path, name, "is missing"),
        E::TensorShape {
            path,
            name,
            expected,
            got,
        } => err(
            &path,
            name,
            format!("has shape {got:?}; config.json's sizes need {expected:?}"),
        ),
        E::UnexpectedTensor { path, name } => err(
            &path,
            name,
            "is not a tensor of the action head config.json describes",
        ),
        E::Format { path, message } => {
            let field = message
                .split('`')
                .nth(1)
                .unwrap_or("(file)")
                .trim_start_matches('`')
                .to_string();
            err(&path, field, message)
        }
        E::Safetensors { path, message } => err(&path, "(safetensors header)", message),
        E::Io { path, source } => Error::Read { path, source },
        other => Error::Gr00tCandle {
            path: fallback.to_path_buf(),
            source: Box::new(other),
        },
    }
}
