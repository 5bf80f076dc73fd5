//! Loading the LeapCubeReorient scene (MuJoCo Playground, `playground==0.2.0` wheel).
//!
//! The playground's `leap_rh_mjx.xml` references ten visual meshes of the LEAP hand from
//! `mujoco_menagerie` that ship in no package. They are used only by geoms of class
//! `visual` (no contact, zero density; every body has an explicit `<inertial>`), so the
//! loader drops, **in memory**, every `<mesh>` asset whose file is missing together with the
//! geoms that use it, and refuses if such a geom could collide or carry mass. The user's
//! files are never modified: the edited XML texts and the asset files are handed to MuJoCo
//! through a virtual file system.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use mujoco_rs::prelude::*;
use mujoco_rs::wrappers::mj_auxiliary::MjVfs;

use crate::error::{Error, Result};

/// Environment variable naming the directory that holds `scene_mjx_cube.xml`.
pub const SCENE_DIR_ENV: &str = "PIR2_LEAP_CUBE_DIR";
/// Top-level scene file inside the scene directory.
pub const SCENE_FILE: &str = "scene_mjx_cube.xml";

/// What the loader did to the scene.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct StripReport {
    /// Names of the mesh assets removed because their file is missing.
    pub meshes: Vec<String>,
    /// Number of visual geoms removed with them.
    pub geoms: usize,
}

/// The scene directory: `explicit`, else `$PIR2_LEAP_CUBE_DIR`.
pub fn scene_dir(explicit: Option<&Path>) -> Result<PathBuf> {
    match explicit {
        Some(p) => Ok(p.to_path_buf()),
        None => std::env::var_os(SCENE_DIR_ENV)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
            .ok_or(Error::SceneDirUnset),
    }
}

/// Load the scene from `dir` (or `$PIR2_LEAP_CUBE_DIR`), stripping visual-only meshes whose
/// files are missing. Returns the compiled model and what was stripped.
pub fn load_model(dir: Option<&Path>) -> Result<(Arc<MjModel>, StripReport)> {
    let dir = scene_dir(dir)?;
    let top = dir.join(SCENE_FILE);
    let mut vfs = MjVfs::new();
    let mut report = StripReport::default();
    let mut seen = BTreeSet::new();
    add_xml(&dir, SCENE_FILE, &mut vfs, &mut report, &mut seen)?;
    let model = MjModel::from_xml_vfs(SCENE_FILE, &vfs).map_err(|e| Error::SceneLoad {
        path: top.clone(),
        message: e.to_string(),
    })?;
    Ok((Arc::new(model), report))
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|source| Error::SceneFile {
        path: path.to_path_buf(),
        source,
    })
}

/// Read one XML file, strip it, add it and the files it references to `vfs`.
fn add_xml(
    dir: &Path,
    rel: &str,
    vfs: &mut MjVfs,
    report: &mut StripReport,
    seen: &mut BTreeSet<String>,
) -> Result<()> {
    if !seen.insert(rel.to_string()) {
        return Ok(());
    }
    let path = dir.join(rel);
    let bytes = read_bytes(&path)?;
    let text = String::from_utf8_lossy(&bytes).into_owned();
    let base = Path::new(rel).parent().unwrap_or(Path::new(""));
    let (text, stripped) = strip_missing_meshes(&text, &|f| dir.join(base).join(f).exists())
        .map_err(|(mesh, file)| Error::PhysicalMeshMissing {
            mesh,
            file: dir.join(base).join(file),
            xml: path.clone(),
        })?;
    report.meshes.extend(stripped.meshes);
    report.geoms += stripped.geoms;
    for file in file_attributes(&text) {
        let file_rel = base.join(&file).to_string_lossy().into_owned();
        if seen.contains(&file_rel) {
            continue;
        }
        if file.ends_with(".xml") {
            add_xml(dir, &file_rel, vfs, report, seen)?;
        } else {
            seen.insert(file_rel.clone());
            let data = read_bytes(&dir.join(&file_rel))?;
            vfs.add_from_buffer(&file_rel, &data)
                .map_err(|e| Error::SceneLoad {
                    path: dir.join(&file_rel),
                    message: e.to_string(),
                })?;
        }
    }
    vfs.add_from_buffer(rel, text.as_bytes())
        .map_err(|e| Error::SceneLoad {
            path,
            message: e.to_string(),
        })?;
    Ok(())
}

/// Every value of a `file="…"` or `file<suffix>="…"` attribute (includes, meshes, textures).
fn file_attributes(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("file") {
        let before_ok = i > 0 && rest.as_bytes()[i - 1].is_ascii_whitespace();
        let after = &rest[i + 4..];
        let name_end = after
            .find(|c: char| !c.is_ascii_alphabetic())
            .unwrap_or(after.len());
        let tail = &after[name_end..];
        if before_ok && tail.starts_with("=\"") {
            if let Some(end) = tail[2..].find('"') {
                out.push(tail[2..2 + end].to_string());
            }
        }
        rest = after;
    }
    out
}

/// Value of attribute `name` inside one element's text.
fn attribute<'a>(element: &'a str, name: &str) -> Option<&'a str> {
    let mut rest = element;
    let pat = format!("{name}=\"");
    while let Some(i) = rest.find(&pat) {
        if i > 0 && rest.as_bytes()[i - 1].is_ascii_whitespace() {
            let v = &rest[i + pat.len()..];
            return v.find('"').map(|e| &v[..e]);
        }
        rest = &rest[i + pat.len()..];
    }
    None
}

/// Byte ranges of all self-closing `<tag …/>` elements, each extended over the leading
/// whitespace of its line so removal leaves no blank lines.
fn elements(text: &str, tag: &str) -> Vec<(usize, usize)> {
    let open = format!("<{tag}");
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(i) = text[from..].find(&open) {
        let start = from + i;
        let after = start + open.len();
        let next = text[after..].chars().next();
        if !matches!(next, Some(c) if c.is_ascii_whitespace()) {
            from = after;
            continue;
        }
        let Some(close) = text[start..].find('>') else {
            break;
        };
        let end = start + close + 1;
        if text[..end].ends_with("/>") {
            let line_start = text[..start].rfind('\n').map_or(0, |n| n + 1);
            let s = if text[line_start..start].trim().is_empty() {
                line_start
            } else {
                start
            };
            let e = if text[end..].starts_with('\n') && s == line_start {
                end + 1
            } else {
                end
            };
            out.push((s, e));
        }
        from = end;
    }
    out
}

/// Remove `<mesh>` assets whose file does not exist (`exists(file)` decides) and the geoms
/// that use them. A geom may only be removed if it is visual-only (class `visual`, or
/// `contype="0" conaffinity="0"` with `density="0"`/`mass="0"`); otherwise the mesh name
/// and file are returned as the error.
pub(crate) fn strip_missing_meshes(
    text: &str,
    exists: &dyn Fn(&str) -> bool,
) -> std::result::Result<(String, StripReport), (String, String)> {
    let mut missing = Vec::new();
    let mut cut: Vec<(usize, usize)> = Vec::new();
    for (s, e) in elements(text, "mesh") {
        let el = &text[s..e];
        if let (Some(name), Some(file)) = (attribute(el, "name"), attribute(el, "file")) {
            if !exists(file) {
                missing.push((name.to_string(), file.to_string()));
                cut.push((s, e));
            }
        }
    }
    let mut report = StripReport::default();
    if missing.is_empty() {
        return Ok((text.to_string(), report));
    }
    for (s, e) in elements(text, "geom") {
        let el = &text[s..e];
        let Some(mesh) = attribute(el, "mesh") else {
            continue;
        };
        let Some((name, file)) = missing.iter().find(|(n, _)| n == mesh) else {
            continue;
        };
        let visual_class = attribute(el, "class") == Some("visual");
        let no_contact = attribute(el, "contype") == Some("0")
            && attribute(el, "conaffinity") == Some("0")
            && (attribute(el, "density") == Some("0") || attribute(el, "mass") == Some("0"));
        if !(visual_class || no_contact) {
            return Err((name.clone(), file.clone()));
        }
        cut.push((s, e));
        report.geoms += 1;
    }
    cut.sort_unstable();
    let mut out = String::with_capacity(text.len());
    let mut pos = 0;
    for (s, e) in cut {
        out.push_str(&text[pos..s]);
        pos = e;
    }
    out.push_str(&text[pos..]);
    report.meshes = missing.into_iter().map(|(n, _)| n).collect();
    Ok((out, report))
}

#[cfg(test)]
mod tests {
    use super::*;

    const XML: &str = r#"<mujoco>
  <asset>
    <mesh name="keep" file="meshes/here.obj"/>
    <mesh name="gone" file="../far/away.obj"/>
  </asset>
  <worldbody>
    <body name="b">
      <geom name="v" class="visual" mesh="gone"/>
      <geom name="k" class="visual" mesh="keep"/>
      <geom type="mesh" mesh="gone" class="visual"
        material="gray"/>
      <geom name="box" type="box" size="1 1 1"/>
    </body>
  </worldbody>
</mujoco>"#;

    #[test]
    fn strips_only_missing_visual_meshes() {
        let (out, rep) = strip_missing_meshes(XML, &|f| f == "meshes/here.obj").unwrap();
        assert_eq!(rep.meshes, vec!["gone".to_string()]);
        assert_eq!(rep.geoms, 2);
        assert!(!out.contains("gone"), "{out}");
        assert!(out.contains(r#"mesh="keep""#));
        assert!(out.contains(r#"name="box""#));
        assert!(!out.contains("\n\n"), "removal left blank lines:\n{out}");
    }

    #[test]
    fn refuses_to_strip_a_colliding_mesh_geom() {
        let xml = XML.replace(
            r#"<geom name="v" class="visual" mesh="gone"/>"#,
            r#"<geom name="v" mesh="gone"/>"#,
        );
        let err = strip_missing_meshes(&xml, &|f| f == "meshes/here.obj").unwrap_err();
        assert_eq!(err, ("gone".to_string(), "../far/away.obj".to_string()));
    }

    #[test]
    fn finds_include_mesh_and_texture_files() {
        let t = r#"<include file="a.xml"/><texture fileup="t/u.png" file="x.png"/><mesh name="m" profile="p"/>"#;
        assert_eq!(file_attributes(t), vec!["a.xml", "t/u.png", "x.png"]);
    }

    #[test]
    fn missing_dir_error_names_path_and_setup_script() {
        let err = load_model(Some(Path::new("/nonexistent/leap_cube"))).unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("/nonexistent/leap_cube/scene_mjx_cube.xml"),
            "{msg}"
        );
        assert!(msg.contains("scripts/setup-native.sh"), "{msg}");
    }
}
