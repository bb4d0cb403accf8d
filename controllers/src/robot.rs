//! The robot model the tick needs: which joints, in which order, within which limits.

use std::collections::HashMap;

use crate::error::Error;
use crate::kinematics::Kinematics;
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
    /// FR3's position-dependent velocity limit: offset and deceleration (0 = constant limit).
    pub dq_offset_rad_s: f64,
    pub ddq_dec_rad_s2: f64,
}

impl JointLimits {
    /// Allowed velocity range at position `q`: constant, or FR3's
    /// upper(q) = min(q̇_max, max(0, −offset + √max(0, 2·q̈_dec·(q_max − q)))), lower mirrored.
    #[inline]
    pub fn velocity_bounds(&self, q: f64) -> (f64, f64) {
        if self.ddq_dec_rad_s2 <= 0.0 {
            return (-self.dq_max_rad_s, self.dq_max_rad_s);
        }
        let side = |room: f64| {
            let v = -self.dq_offset_rad_s + (2.0 * self.ddq_dec_rad_s2 * room.max(0.0)).sqrt();
            v.clamp(0.0, self.dq_max_rad_s)
        };
        (-side(q - self.q_min_rad), side(self.q_max_rad - q))
    }
}

/// Which published limit set applies. Kinematics always come from the URDF (Panda and FR3
/// share them); the profile adds what URDF cannot say and, for FR3, replaces its limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Profile {
    Panda,
    Fr3,
}

impl Profile {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "panda" => Some(Self::Panda),
            "fr3" => Some(Self::Fr3),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Panda => "panda",
            Self::Fr3 => "fr3",
        }
    }

    /// Published Cartesian limits of the TCP.
    pub fn cartesian(self) -> CartesianLimits {
        match self {
            Self::Panda => CartesianLimits { v_m_s: 1.7, a_m_s2: 13.0, w_rad_s: 2.5, dw_rad_s2: 25.0 },
            Self::Fr3 => CartesianLimits { v_m_s: 3.0, a_m_s2: 9.0, w_rad_s: 2.5, dw_rad_s2: 17.0 },
        }
    }

    fn apply(self, i: usize, urdf: JointLimits) -> JointLimits {
        match self {
            Self::Panda => JointLimits { ddq_max_rad_s2: PANDA_DDQ_MAX[i], jerk_max_rad_s3: PANDA_JERK_MAX[i], ..urdf },
            Self::Fr3 => JointLimits {
                q_min_rad: FR3_Q_MIN[i],
                q_max_rad: FR3_Q_MAX[i],
                dq_max_rad_s: FR3_DQ_MAX[i],
                ddq_max_rad_s2: 10.0,
                jerk_max_rad_s3: 5000.0,
                dq_offset_rad_s: FR3_DQ_OFFSET[i],
                ddq_dec_rad_s2: FR3_DDQ_DEC[i],
            },
        }
    }
}

/// TCP speed and acceleration limits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CartesianLimits {
    pub v_m_s: f64,
    pub a_m_s2: f64,
    pub w_rad_s: f64,
    pub dw_rad_s2: f64,
}

/// Joint names, limits, kinematics and the gripper of a 7-DoF arm.
#[derive(Debug, Clone)]
pub struct RobotModel {
    pub name: String,
    pub profile: Profile,
    pub kin: Kinematics,
    pub cartesian: CartesianLimits,
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
const FR3_Q_MAX: [f64; N] = [2.9007, 1.8361, 2.9007, -0.1169, 2.8763, 4.6216, 3.0508];
const FR3_Q_MIN: [f64; N] = [-2.9007, -1.8361, -2.9007, -3.0770, -2.8763, 0.4398, -3.0508];
const FR3_DQ_MAX: [f64; N] = [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26];
const FR3_DQ_OFFSET: [f64; N] = [0.6599, 0.2517, 0.2000, 0.3533, 0.5757, 0.4878, 0.4628];
const FR3_DDQ_DEC: [f64; N] = [6.0, 2.585, 3.5, 4.0, 17.0, 5.5, 17.0];

impl RobotModel {
    /// Reads the arm chain from the root link down to `tcp_link`: its 7 revolute joints in order,
    /// and the first non-mimic prismatic joint below the chain as the gripper. `profile` adds the
    /// limits URDF cannot express (and for FR3 replaces the URDF's).
    pub fn from_urdf_str(xml: &str, tcp_link: &str, profile: Profile) -> Result<Self, Error> {
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
            dq_offset_rad_s: 0.0,
            ddq_dec_rad_s2: 0.0,
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
            let urdf = JointLimits {
                q_min_rad: l.lower,
                q_max_rad: l.upper,
                dq_max_rad_s: l.velocity,
                ddq_max_rad_s2: 0.0,
                jerk_max_rad_s3: 0.0,
                dq_offset_rad_s: 0.0,
                ddq_dec_rad_s2: 0.0,
            };
            joints[i] = profile.apply(i, urdf);
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
        let kin = Kinematics::from_urdf(&robot, tcp_link, &joint_names)?;
        Ok(Self {
            name: robot.name.clone(),
            profile,
            kin,
            cartesian: profile.cartesian(),
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
