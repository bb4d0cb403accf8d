use std::fmt;

/// Errors while building a robot model.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    #[error("URDF does not parse: {0}")]
    Urdf(String),
    #[error("URDF has no link named '{link}' (links: {known})")]
    NoSuchLink { link: String, known: String },
    #[error("URDF chain from the root to '{link}' has {found} revolute joints, expected 7")]
    WrongDof { link: String, found: usize },
    #[error("URDF joint '{joint}' has an unusable limit: {detail}")]
    BadLimit { joint: String, detail: String },
    #[error("URDF has no prismatic finger joint under link '{link}'")]
    NoFinger { link: String },
}

/// A short message kept inline, so that building a rejection in the tick allocates nothing.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Text {
    buf: [u8; 100],
    len: u8,
}

impl Text {
    pub fn of(args: fmt::Arguments<'_>) -> Self {
        let mut t = Self { buf: [0; 100], len: 0 };
        let _ = fmt::write(&mut t, args);
        t
    }

    pub fn as_str(&self) -> &str {
        std::str::from_utf8(&self.buf[..usize::from(self.len)]).unwrap_or("")
    }
}

impl fmt::Write for Text {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        // Whole characters only, so the buffer always holds valid UTF-8.
        for c in s.chars() {
            let (at, n) = (usize::from(self.len), c.len_utf8());
            if at + n > self.buf.len() {
                return Ok(());
            }
            c.encode_utf8(&mut self.buf[at..]);
            self.len += n as u8;
        }
        Ok(())
    }
}

impl fmt::Debug for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl fmt::Display for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Why a chunk was refused. Never clipped into acceptance: the agent gets this back.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Rejection {
    Empty,
    TooLong {
        len: usize,
        max: usize,
    },
    NotFinite {
        waypoint: usize,
        index: usize,
    },
    BadFrequency {
        freq_hz: f64,
        min_hz: f64,
        max_hz: f64,
    },
    TooSlow {
        waypoint: usize,
        duration_s: f64,
        max_s: f64,
    },
    JointOutOfRange {
        waypoint: usize,
        joint: usize,
        value: f64,
        min: f64,
        max: f64,
    },
    GripperOutOfRange {
        waypoint: usize,
        value: f64,
    },
    UnknownControlType(u32),
    UnsupportedControlType(&'static str),
    ControlTypeLocked {
        locked: &'static str,
        requested: &'static str,
    },
    Busy,
    /// No joint configuration within the limits puts the TCP at this ee_pose waypoint.
    Unreachable {
        waypoint: usize,
        position_error_m: f64,
        rotation_error_rad: f64,
        /// Bit j set: joint j+1 of the best solution found is at its limit.
        at_limits: u8,
    },
    /// The waypoint, or the path to it, collides or leaves the workspace.
    Unsafe {
        waypoint: usize,
        detail: Text,
    },
    /// The arm is braking after a safety check stopped the previous motion.
    Halting,
    UnknownRequestKind(u32),
    /// A waypoint is further from the previous one (the first: from the measured position)
    /// than the configured step cap allows.
    StepTooLarge {
        waypoint: usize,
        quantity: StepQuantity,
        value: f64,
        max: f64,
    },
    /// A TCP turn over the cap in an ee_pose chunk whose waypoints turn the hand more than half
    /// a turn further than the direct way from start to end: axis-angle vectors interpolated
    /// component by component across the ±π wrap.
    LongWayRound {
        waypoint: usize,
        value: f64,
        max: f64,
        turn_rad: f64,
        direct_rad: f64,
    },
}

/// What a step cap limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StepQuantity {
    /// One arm joint (0-based), rad.
    Joint(usize),
    /// TCP translation, m.
    TcpTranslation,
    /// TCP rotation, rad.
    TcpRotation,
}

impl Rejection {
    /// A short stable name of the reason, for counting.
    pub fn kind(&self) -> &'static str {
        match self {
            Self::Empty => "empty",
            Self::TooLong { .. } => "too_long",
            Self::NotFinite { .. } => "not_finite",
            Self::BadFrequency { .. } => "bad_frequency",
            Self::TooSlow { .. } => "too_slow",
            Self::JointOutOfRange { .. } => "joint_out_of_range",
            Self::GripperOutOfRange { .. } => "gripper_out_of_range",
            Self::UnknownControlType(_) => "unknown_control_type",
            Self::UnsupportedControlType(_) => "unsupported_control_type",
            Self::ControlTypeLocked { .. } => "control_type_locked",
            Self::Busy => "busy",
            Self::Unreachable { .. } => "unreachable",
            Self::Unsafe { .. } => "unsafe",
            Self::Halting => "halting",
            Self::UnknownRequestKind(_) => "unknown_request_kind",
            Self::StepTooLarge { .. } => "step_too_large",
            Self::LongWayRound { .. } => "rotation_wrap",
        }
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Empty => write!(f, "actions is empty: send at least one waypoint"),
            Self::TooLong { len, max } => {
                write!(f, "actions has {len} waypoints, at most {max} are accepted: split the chunk")
            }
            Self::NotFinite { waypoint, index } => {
                write!(f, "actions[{waypoint}][{index}] is not a finite number (NaN or infinity)")
            }
            Self::BadFrequency { freq_hz, min_hz, max_hz } => {
                write!(f, "freq {freq_hz} Hz is not usable: give \"\" (20 Hz) or a rate in [{min_hz}, {max_hz}] Hz")
            }
            Self::TooSlow { waypoint, duration_s, max_s } => write!(
                f,
                "the chunk would take {duration_s:.1} s by actions[{waypoint}]; one chunk may take at most {max_s} s: raise freq or split it"
            ),
            Self::JointOutOfRange { waypoint, joint, value, min, max } => {
                let by = if value < min { min - value } else { value - max };
                write!(
                    f,
                    "actions[{waypoint}] joint {} = {value:.4} rad is outside the allowed range [{min:.4}, {max:.4}] rad by {by:.4} rad",
                    joint + 1
                )
            }
            Self::GripperOutOfRange { waypoint, value } => {
                write!(f, "actions[{waypoint}] gripper = {value} is outside [-1 (open), +1 (closed)]")
            }
            Self::UnknownControlType(t) => write!(f, "unknown control type code {t}: use \"joint\" or \"ee_pose\""),
            Self::UnsupportedControlType(t) => write!(f, "control type \"{t}\" is not available in this runtime"),
            Self::ControlTypeLocked { locked, requested } => {
                write!(f, "this episode uses \"{locked}\" control; \"{requested}\" is rejected until reset()")
            }
            Self::Busy => write!(f, "another client's request is executing: wait for it to finish"),
            Self::Unreachable { waypoint, position_error_m, rotation_error_rad, at_limits } => {
                write!(
                    f,
                    "actions[{waypoint}] is not reachable within the joint limits (best found: {:.1} mm, {:.2} deg away",
                    position_error_m * 1e3,
                    rotation_error_rad.to_degrees()
                )?;
                for (i, j) in (0..8).filter(|j| at_limits & (1 << j) != 0).enumerate() {
                    write!(f, "{}{}", if i == 0 { "; joints at their limits: " } else { ", " }, j + 1)?;
                }
                if *at_limits == 0 {
                    write!(f, "; no joint is at its limit: the pose is out of the arm's reach, or needs another arm configuration")?;
                }
                write!(f, ")")
            }
            Self::Unsafe { waypoint, detail } => write!(f, "actions[{waypoint}] is refused: {detail}"),
            Self::Halting => write!(f, "the arm is braking after a stop (safety check or contact reflex): send the chunk again once it rests"),
            Self::UnknownRequestKind(k) => write!(f, "unknown request kind {k}"),
            Self::StepTooLarge { waypoint, quantity, value, max } => {
                let from = if *waypoint == 0 { "the measured position" } else { "the previous waypoint" };
                let (what, unit) = match quantity {
                    StepQuantity::Joint(j) => (Text::of(format_args!("joint {} changes", j + 1)), "rad"),
                    StepQuantity::TcpTranslation => (Text::of(format_args!("the TCP moves")), "m"),
                    StepQuantity::TcpRotation => (Text::of(format_args!("the TCP turns")), "rad"),
                };
                let parts = (value / max).ceil().max(2.0);
                write!(
                    f,
                    "actions[{waypoint}]: {what} by {value:.4} {unit} from {from}; the cap is {max:.4} {unit} per waypoint ({:.4} {unit} over): split this step into at least {parts:.0} waypoints",
                    value - max
                )
            }
            Self::LongWayRound { waypoint, value, max, turn_rad, direct_rad } => write!(
                f,
                "actions[{waypoint}]: the chunk turns the TCP {turn_rad:.1} rad in all (this step {value:.2} rad, cap {max:.2}) to end {direct_rad:.2} rad from where it starts, the long way round: probably rotation vectors interpolated across the ±π wrap: use robo_perception.interpolate_poses, not more waypoints (to turn more than three quarters of a turn on purpose, use two chunks)"
            ),
        }
    }
}
