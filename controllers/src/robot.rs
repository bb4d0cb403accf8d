//! The robot model the tick needs: which joints, in which order, within which limits.

use std::collections::HashMap;

use crate::error::Error;
use crate::N;

/// Limits of one arm joint. Position and velocity come from the URDF; acceleration and jerk,
/// which URDF cannot express, from the robot's published figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointLimits {
    pub q_min_rad: f64,
    pub q_max_rad: f64,
    pub dq_max_rad_s: f64,
    pub ddq_max_rad_s2: f64,
    pub jerk_max_rad_s3: f64,
}

/// Joint names, limits and the gripper of a 7-DoF arm.
#[derive(Debug, Clone)]
pub struct RobotModel {
    pub name: String,
    pub joint_names: [String; N],
    pub joints: [JointLimits; N],
    pub finger_joint: String,
    /// Opening of one finger when fully open, m.
    pub finger_max_m: f64,
    pub finger_speed_m_s: f64,
    pub tcp_link: String,
}

/// Panda acceleration and jerk limits (rad/s², rad/s³), from Franka's published figures.
pub const PANDA_DDQ_MAX: [f64; N] = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0];
pub const PANDA_JERK_MAX: [f64; N] = [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0];

impl RobotModel {
    /// Reads the arm chain from the root link down to `tcp_link`: its 7 revolute joints in order,
    /// and the first non-mimic prismatic joint below the chain as the gripper.
    pub fn from_urdf_str(xml: &str, tcp_link: &str, ddq_max: [f64; N], jerk_max: [f64; N]) -> Result<Self, Error> {
        let robot = urdf_rs::read_from_string(xml).map_err(|e| Error::Urdf(e.to_string()))?;
        if !robot.links.iter().any(|l| l.name == tcp_link) {
            let known = robot.links.iter().map(|l| l.name.as_str()).collect::<Vec<_>>().join(", ");
            return Err(Error::NoSuchLink { link: tcp_link.into(), known });
        }
        let by_child: HashMap<&str, &urdf_rs::Joint> =
            robot.joints.iter().map(|j| (j.child.link.as_str(), j)).collect();
        let mut chain = Vec::new();
        let mut link = tcp_link;
        while let Some(j) = by_child.get(link) {
            chain.push(*j);
            link = j.parent.link.as_str();
            if chain.len() > robot.joints.len() {
                return Err(Error::Urdf("the joint graph has a cycle".into()));
            }
        }
        chain.reverse();
        let revolute: Vec<&urdf_rs::Joint> =
            chain.iter().copied().filter(|j| matches!(j.joint_type, urdf_rs::JointType::Revolute)).collect();
        if revolute.len() != N {
            return Err(Error::WrongDof { link: tcp_link.into(), found: revolute.len() });
        }
        let mut joints = [JointLimits {
            q_min_rad: 0.0,
            q_max_rad: 0.0,
            dq_max_rad_s: 0.0,
            ddq_max_rad_s2: 0.0,
            jerk_max_rad_s3: 0.0,
        }; N];
        let mut joint_names: [String; N] = Default::default();
        for (i, j) in revolute.iter().enumerate() {
            let l = &j.limit;
            let bad = |detail: &str| Error::BadLimit { joint: j.name.clone(), detail: detail.into() };
            if !(l.lower.is_finite() && l.upper.is_finite() && l.lower < l.upper) {
                return Err(bad("lower must be finite and below upper"));
            }
            if !(l.velocity.is_finite() && l.velocity > 0.0) {
                return Err(bad("velocity must be positive"));
            }
            joints[i] = JointLimits {
                q_min_rad: l.lower,
                q_max_rad: l.upper,
                dq_max_rad_s: l.velocity,
                ddq_max_rad_s2: ddq_max[i],
                jerk_max_rad_s3: jerk_max[i],
            };
            joint_names[i] = j.name.clone();
        }
        // The gripper hangs below the last arm joint, off the TCP chain itself.
        let arm_links: Vec<&str> = chain.iter().map(|j| j.child.link.as_str()).collect();
        let finger = robot.joints.iter().find(|j| {
            matches!(j.joint_type, urdf_rs::JointType::Prismatic)
                && j.mimic.is_none()
                && arm_links.contains(&j.parent.link.as_str())
        });
        let Some(finger) = finger else {
            return Err(Error::NoFinger { link: tcp_link.into() });
        };
        if !(finger.limit.upper > finger.limit.lower && finger.limit.velocity > 0.0) {
            return Err(Error::BadLimit {
                joint: finger.name.clone(),
                detail: "finger range or speed is empty".into(),
            });
        }
        Ok(Self {
            name: robot.name.clone(),
            joint_names,
            joints,
            finger_joint: finger.name.clone(),
            finger_max_m: finger.limit.upper,
            finger_speed_m_s: finger.limit.velocity,
            tcp_link: tcp_link.into(),
        })
    }

    /// Maps the agent's gripper value (−1 open … +1 closed) to one finger's opening in metres.
    pub fn finger_from_gripper(&self, g: f64) -> f64 {
        self.finger_max_m * (1.0 - g.clamp(-1.0, 1.0)) * 0.5
    }

    /// Inverse of [`Self::finger_from_gripper`].
    pub fn gripper_from_finger(&self, finger_m: f64) -> f64 {
        (1.0 - 2.0 * finger_m / self.finger_max_m).clamp(-1.0, 1.0)
    }
}
