//! The compiled scene plus the indices the task needs, shared by the environment and the
//! expert (one `MjModel`, many `MjData`).

use std::path::Path;
use std::sync::Arc;

use mujoco_rs::prelude::*;

use super::scene::{load_model, StripReport};
use crate::error::{Error, Result};

/// Number of hand joints / actuators.
pub const NU: usize = 16;

/// The LeapCubeReorient model and the addresses of everything the task reads.
#[derive(Debug, Clone)]
pub struct LeapModel {
    pub(crate) model: Arc<MjModel>,
    /// `qpos` address of the joint driven by actuator `i`.
    pub(crate) hand_qadr: [usize; NU],
    /// `qvel` address of the joint driven by actuator `i`.
    pub(crate) hand_dadr: [usize; NU],
    /// `qpos` address of the cube free joint (3 position + 4 quaternion).
    pub(crate) cube_qadr: usize,
    /// `qvel` address of the cube free joint.
    pub(crate) cube_dadr: usize,
    pub(crate) sens_cube_pos: usize,
    pub(crate) sens_cube_quat: usize,
    pub(crate) sens_palm_pos: usize,
    /// World position of the grasp site (fixed: it sits on the static mount).
    pub(crate) grasp_pos: [f64; 3],
    /// Home pose of the hand (keyframe `home`), actuator order.
    pub(crate) home: [f64; NU],
    /// Mocap position of the goal cube in keyframe `home`.
    pub(crate) home_mpos: [f64; 3],
    pub(crate) lo: [f64; NU],
    pub(crate) hi: [f64; NU],
    pub(crate) strip: StripReport,
}

fn id(m: &MjModel, kind: MjtObjBase, label: &'static str, name: &str) -> Result<usize> {
    m.name_to_id(kind, name)
        .ok_or_else(|| Error::MissingElement {
            kind: label,
            name: name.to_string(),
        })
}

impl LeapModel {
    /// Load from `dir`, or from `$PIR2_LEAP_CUBE_DIR` when `None`.
    pub fn load(dir: Option<&Path>) -> Result<Self> {
        let (model, strip) = load_model(dir)?;
        Self::from_model(model, strip)
    }

    fn from_model(model: Arc<MjModel>, strip: StripReport) -> Result<Self> {
        let m: &MjModel = &model;
        let f = m.ffi();
        if f.nu as usize != NU {
            return Err(Error::LeapShape {
                what: "actuators",
                expected: NU,
                got: f.nu as usize,
            });
        }
        let mut hand_qadr = [0; NU];
        let mut hand_dadr = [0; NU];
        let mut lo = [0.0; NU];
        let mut hi = [0.0; NU];
        for i in 0..NU {
            let j = m.actuator_trnid()[i][0] as usize;
            hand_qadr[i] = m.jnt_qposadr()[j] as usize;
            hand_dadr[i] = m.jnt_dofadr()[j] as usize;
            lo[i] = m.actuator_ctrlrange()[i][0];
            hi[i] = m.actuator_ctrlrange()[i][1];
        }
        let cube_j = id(m, MjtObjBase::mjOBJ_JOINT, "joint", "cube_freejoint")?;
        let sensor = |name: &str| -> Result<usize> {
            Ok(m.sensor_adr()[id(m, MjtObjBase::mjOBJ_SENSOR, "sensor", name)?] as usize)
        };
        let key = id(m, MjtObjBase::mjOBJ_KEY, "keyframe", "home")?;
        let nq = f.nq as usize;
        let kq = &m.key_qpos()[key * nq..(key + 1) * nq];
        let mut home = [0.0; NU];
        for i in 0..NU {
            home[i] = kq[hand_qadr[i]];
        }
        let nm = 3 * f.nmocap as usize;
        let km = &m.key_mpos()[key * nm..key * nm + 3];
        let site = id(m, MjtObjBase::mjOBJ_SITE, "site", "grasp_site")?;
        let mut data = MjData::new(model.clone());
        data.forward();
        let grasp_pos = data.site_xpos()[site];
        Ok(Self {
            hand_qadr,
            hand_dadr,
            cube_qadr: m.jnt_qposadr()[cube_j] as usize,
            cube_dadr: m.jnt_dofadr()[cube_j] as usize,
            sens_cube_pos: sensor("cube_position")?,
            sens_cube_quat: sensor("cube_orientation")?,
            sens_palm_pos: sensor("palm_position")?,
            grasp_pos,
            home,
            home_mpos: [km[0], km[1], km[2]],
            lo,
            hi,
            strip,
            model,
        })
    }

    /// The compiled MuJoCo model.
    pub fn mj_model(&self) -> &Arc<MjModel> {
        &self.model
    }

    /// What the loader stripped from the scene.
    pub fn strip_report(&self) -> &StripReport {
        &self.strip
    }

    /// The hand's home pose (keyframe `home`), actuator order.
    pub fn home(&self) -> &[f64; NU] {
        &self.home
    }

    /// Control range `(lower, upper)` per actuator.
    pub fn ctrl_range(&self) -> (&[f64; NU], &[f64; NU]) {
        (&self.lo, &self.hi)
    }

    /// World position of the grasp site (the "palm position" of the observation).
    pub fn grasp_pos(&self) -> [f64; 3] {
        self.grasp_pos
    }

    /// A fresh `MjData` for this model.
    pub fn make_data(&self) -> MjData<Arc<MjModel>> {
        MjData::new(self.model.clone())
    }

    /// Physics time step (s).
    pub fn timestep(&self) -> f64 {
        self.model.opt().timestep
    }
}
