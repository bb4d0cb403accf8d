//! The physics side: a compiled scene, one step per command sample, reset to the scene's
//! initial state, and the measured robot state a real arm would report.

use std::sync::Arc;

use controllers::math;
use controllers::RobotModel;
use ipc_schema::{JointCommand, Pose, SimState, N_JOINTS};
use mujoco_rs::mujoco_c::{mj_forward, mj_resetData};
use mujoco_rs::prelude::*;

use crate::mjcf;
use crate::scene::Scene;

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SimError {
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    #[error("robot model: {0}")]
    Robot(#[from] controllers::Error),
    #[error("scene to MJCF: {0}")]
    Mjcf(#[from] mjcf::MjcfError),
    #[error("MuJoCo refused the compiled model: {0}")]
    Compile(String),
    #[error("compiled model lacks {0}")]
    Missing(String),
}

/// Indices into the compiled model, resolved once.
#[derive(Debug, Clone)]
pub struct Layout {
    pub arm_qpos: [usize; N_JOINTS],
    pub arm_dof: [usize; N_JOINTS],
    pub finger_qpos: Vec<usize>,
    pub pos_act: [usize; N_JOINTS],
    pub vel_act: [usize; N_JOINTS],
    pub grip_act: usize,
    pub tcp_site: usize,
    pub base_body: usize,
    pub cameras: Vec<(String, usize)>,
}

pub struct Sim {
    pub scene: Scene,
    pub robot: RobotModel,
    pub mjcf: String,
    pub model: Arc<MjModel>,
    pub data: MjData<Arc<MjModel>>,
    pub layout: Layout,
    home_q: [f64; N_JOINTS],
    home_finger: f64,
    /// Commands computed from states older than this are stale (sent before a reset landed).
    pub reset_state_seq: u64,
}

fn id(model: &MjModel, kind: MjtObjBase, name: &str) -> Result<usize, SimError> {
    model.name_to_id(kind, name).ok_or_else(|| SimError::Missing(format!("{kind:?} '{name}'")))
}

impl Sim {
    pub fn load(scene_path: &std::path::Path) -> Result<Self, SimError> {
        let scene = Scene::load(scene_path)?;
        let urdf = std::fs::read_to_string(&scene.robot.urdf)
            .map_err(|source| crate::scene::SceneError::Urdf { path: scene.robot.urdf.clone(), source })?;
        let robot = RobotModel::from_urdf_str(&urdf, &scene.robot.tcp_link, scene.robot.profile())?;
        let xml = mjcf::compile(&scene, &urdf, &robot)?;
        let model = Arc::new(MjModel::from_xml_string(&xml).map_err(|e| SimError::Compile(format!("{e}")))?);
        let m: &MjModel = &model;
        let joint = |n: &str| id(m, MjtObjBase::mjOBJ_JOINT, n);
        let mut layout = Layout {
            arm_qpos: [0; N_JOINTS],
            arm_dof: [0; N_JOINTS],
            finger_qpos: Vec::new(),
            pos_act: [0; N_JOINTS],
            vel_act: [0; N_JOINTS],
            grip_act: id(m, MjtObjBase::mjOBJ_ACTUATOR, mjcf::GRIPPER_ACTUATOR)?,
            tcp_site: id(m, MjtObjBase::mjOBJ_SITE, mjcf::TCP_SITE)?,
            base_body: 0,
            cameras: Vec::new(),
        };
        let f = m.ffi();
        // SAFETY: the address arrays hold njnt entries and the ids come from name lookups.
        let (qposadr, dofadr) = unsafe {
            (
                std::slice::from_raw_parts(f.jnt_qposadr, f.njnt as usize),
                std::slice::from_raw_parts(f.jnt_dofadr, f.njnt as usize),
            )
        };
        for (i, name) in robot.joint_names.iter().enumerate() {
            let j = joint(name)?;
            layout.arm_qpos[i] = qposadr[j] as usize;
            layout.arm_dof[i] = dofadr[j] as usize;
            layout.pos_act[i] = id(m, MjtObjBase::mjOBJ_ACTUATOR, &format!("{name}_pos"))?;
            layout.vel_act[i] = id(m, MjtObjBase::mjOBJ_ACTUATOR, &format!("{name}_vel"))?;
        }
        let urdf_robot = urdf_rs::read_from_string(&urdf).map_err(|e| SimError::Compile(e.to_string()))?;
        for j in urdf_robot.joints.iter().filter(|j| {
            j.name == robot.finger_joint || j.mimic.as_ref().is_some_and(|mm| mm.joint == robot.finger_joint)
        }) {
            layout.finger_qpos.push(qposadr[joint(&j.name)?] as usize);
        }
        let root = robot
            .joint_names
            .first()
            .and_then(|n| urdf_robot.joints.iter().find(|j| &j.name == n))
            .map(|j| j.parent.link.clone());
        layout.base_body = id(m, MjtObjBase::mjOBJ_BODY, &root.unwrap_or_default())?;
        for c in &scene.cameras {
            layout.cameras.push((c.name.clone(), id(m, MjtObjBase::mjOBJ_CAMERA, &c.name)?));
        }
        let home_q = scene.robot.initial_joints_rad;
        let home_finger = robot.finger_from_gripper(scene.robot.initial_gripper);
        let data = MjData::new(model.clone());
        let mut sim = Self { scene, robot, mjcf: xml, model, data, layout, home_q, home_finger, reset_state_seq: 0 };
        sim.reset();
        Ok(sim)
    }

    /// Restores the robot and every object to the scene's initial state.
    pub fn reset(&mut self) {
        // SAFETY: the live model/data pair of this Sim.
        unsafe { mj_resetData(self.model.ffi(), self.data.ffi_mut()) };
        let home_q = self.home_q;
        let finger = self.home_finger;
        let l = self.layout.clone();
        {
            let qpos = self.qpos_mut();
            for i in 0..N_JOINTS {
                qpos[l.arm_qpos[i]] = home_q[i];
            }
            for &a in &l.finger_qpos {
                qpos[a] = finger;
            }
        }
        let ctrl = self.ctrl_mut();
        for i in 0..N_JOINTS {
            ctrl[l.pos_act[i]] = home_q[i];
            ctrl[l.vel_act[i]] = 0.0;
        }
        ctrl[l.grip_act] = finger;
        // SAFETY: the model/data pair of this Sim, taken afresh after the borrows above ended.
        unsafe { mj_forward(self.model.ffi(), self.data.ffi_mut()) };
    }

    fn slice_mut(&mut self, f: impl Fn(&mut mujoco_rs::mujoco_c::mjData) -> (*mut f64, usize)) -> &mut [f64] {
        // SAFETY: the pointer/length pairs come from mjData arrays sized by the model.
        unsafe {
            let (p, n) = f(self.data.ffi_mut());
            std::slice::from_raw_parts_mut(p, n)
        }
    }

    pub fn qpos_mut(&mut self) -> &mut [f64] {
        let nq = self.model.ffi().nq as usize;
        self.slice_mut(|d| (d.qpos, nq))
    }

    pub fn qpos(&self) -> &[f64] {
        // SAFETY: qpos holds nq values.
        unsafe { std::slice::from_raw_parts(self.data.ffi().qpos, self.model.ffi().nq as usize) }
    }

    fn ctrl_mut(&mut self) -> &mut [f64] {
        let nu = self.model.ffi().nu as usize;
        self.slice_mut(|d| (d.ctrl, nu))
    }

    /// Applies one command and advances physics by one timestep.
    pub fn step(&mut self, cmd: &JointCommand) {
        let l = self.layout.clone();
        let finger_max = self.robot.finger_max_m;
        let fresh = cmd.state_seq >= self.reset_state_seq;
        let ctrl = self.ctrl_mut();
        // Commands computed before the latest reset would yank the arm back: hold instead.
        if fresh {
            for i in 0..N_JOINTS {
                if cmd.q_rad[i].is_finite() && cmd.dq_rad_s[i].is_finite() {
                    ctrl[l.pos_act[i]] = cmd.q_rad[i];
                    ctrl[l.vel_act[i]] = cmd.dq_rad_s[i];
                }
            }
            if cmd.finger_m.is_finite() {
                ctrl[l.grip_act] = cmd.finger_m.clamp(0.0, finger_max);
            }
        }
        self.data.step();
    }

    pub fn time_s(&self) -> f64 {
        self.data.ffi().time
    }

    /// World pose of the robot base body.
    pub fn world_from_base(&self) -> ([f64; 3], math::Quat) {
        let d = self.data.ffi();
        let b = self.layout.base_body;
        // SAFETY: xpos/xquat hold nbody entries; base_body is a valid body id.
        unsafe {
            let p = std::slice::from_raw_parts(d.xpos.add(3 * b), 3);
            let q = std::slice::from_raw_parts(d.xquat.add(4 * b), 4);
            ([p[0], p[1], p[2]], [q[1], q[2], q[3], q[0]])
        }
    }

    /// The measured robot, in the robot base frame.
    pub fn measure(&self, seq: u64, command_seq: u64, reset_id: u64) -> SimState {
        let d = self.data.ffi();
        let l = &self.layout;
        let qpos = self.qpos();
        // SAFETY: qvel holds nv values; site arrays hold nsite entries.
        let (qvel, site_p, site_m) = unsafe {
            (
                std::slice::from_raw_parts(d.qvel, self.model.ffi().nv as usize),
                std::slice::from_raw_parts(d.site_xpos.add(3 * l.tcp_site), 3),
                std::slice::from_raw_parts(d.site_xmat.add(9 * l.tcp_site), 9),
            )
        };
        let mut s = SimState { seq, command_seq, reset_id, sim_time_s: d.time, ..Default::default() };
        for i in 0..N_JOINTS {
            s.q_rad[i] = qpos[l.arm_qpos[i]];
            s.dq_rad_s[i] = qvel[l.arm_dof[i]];
        }
        s.finger_m = l.finger_qpos.first().map(|&a| qpos[a]).unwrap_or(0.0);
        s.finger_max_m = self.robot.finger_max_m;
        let mut m = [0.0; 9];
        m.copy_from_slice(site_m);
        let world_from_tcp = ([site_p[0], site_p[1], site_p[2]], math::quat_from_mat(&m));
        let (p, q) = math::compose(math::inverse(self.world_from_base()), world_from_tcp);
        s.base_from_tcp = Pose { position_m: p, quat_xyzw: q };
        s
    }
}
