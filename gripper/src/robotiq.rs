//! The Robotiq 2F-85's register map and its Modbus RTU frames, without I/O.
//!
//! The gripper is Modbus slave 9 (by default) at 115200 baud, 8N1. Three "robot output"
//! registers from 0x03E8 take the request (written with function 16); three "robot input"
//! registers from 0x07D0 hold the status (read with function 3). Each register carries two
//! bytes, high byte first:
//!
//! | byte | output (request) | input (status) |
//! |---|---|---|
//! | 0 | action: bit 0 `rACT` activate, bit 3 `rGTO` go to position, bit 4 `rATR` auto-release | status: bit 0 `gACT`, bit 3 `gGTO`, bits 4–5 `gSTA` (0 reset, 1 activating, 3 ready), bits 6–7 `gOBJ` |
//! | 1 | reserved | reserved |
//! | 2 | reserved | fault: low nibble `gFLT`, high nibble `kFLT` |
//! | 3 | `rPR` position request (0 open … 255 closed) | `gPR` echo of the request |
//! | 4 | `rSP` speed | `gPO` position |
//! | 5 | `rFR` force | `gCU` current, × 10 mA |
//!
//! `gOBJ`: 0 moving, 1 stopped by contact while opening, 2 stopped by contact while closing
//! (an object is held), 3 at the requested position (nothing held, or the object was lost).

use rmodbus::client::ModbusRequest;
use rmodbus::{ErrorKind, ModbusProto};

/// First request register.
pub const OUTPUT_REGISTER: u16 = 0x03E8;
/// First status register.
pub const INPUT_REGISTER: u16 = 0x07D0;

/// What the driver asks of the gripper (the three output registers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Command {
    pub activate: bool,
    pub go: bool,
    pub position: u8,
    pub speed: u8,
    pub force: u8,
}

impl Command {
    pub fn registers(&self) -> [u16; 3] {
        let action = u8::from(self.activate) | (u8::from(self.go) << 3);
        [u16::from(action) << 8, u16::from(self.position), (u16::from(self.speed) << 8) | u16::from(self.force)]
    }
}

/// The gripper's status (the three input registers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Status {
    pub activated: bool,
    pub going: bool,
    /// `gSTA`: 0 reset, 1 activating, 3 ready.
    pub activation: u8,
    /// `gOBJ`.
    pub object: u8,
    /// `gFLT`.
    pub fault: u8,
    /// `kFLT` (the controller's own faults).
    pub controller_fault: u8,
    pub requested: u8,
    pub position: u8,
    /// Motor current, mA.
    pub current_ma: u32,
}

impl Status {
    /// From the three status registers (a read of fewer fills the rest with zeros).
    pub fn from_registers(r: &[u16]) -> Self {
        let b = |i: usize| -> u8 {
            let reg = r.get(i / 2).copied().unwrap_or(0);
            if i.is_multiple_of(2) {
                (reg >> 8) as u8
            } else {
                reg as u8
            }
        };
        let s = b(0);
        Self {
            activated: s & 1 != 0,
            going: s & 0x08 != 0,
            activation: (s >> 4) & 0x03,
            object: s >> 6,
            fault: b(2) & 0x0F,
            controller_fault: b(2) >> 4,
            requested: b(3),
            position: b(4),
            current_ma: u32::from(b(5)) * 10,
        }
    }

    pub fn ready(&self) -> bool {
        self.activated && self.activation == 3
    }

    /// What the manual says a fault means for the gripper's operation.
    pub fn fault_class(&self) -> FaultClass {
        match (self.controller_fault, self.fault) {
            (k, _) if k != 0 => FaultClass::Major,
            (_, 0x0A..=0x0F) => FaultClass::Major,
            (_, 0x08 | 0x09) => FaultClass::Minor,
            _ => FaultClass::None,
        }
    }

    /// The fault byte as published (`GripperState::fault`): `kFLT` in the high nibble, `gFLT`
    /// in the low one, so that a controller fault alone is not read as "no fault".
    pub fn fault_code(&self) -> u8 {
        (self.controller_fault << 4) | self.fault
    }

    /// The fault in words: the code, the manual's meaning and, when set, `kFLT`.
    pub fn fault_text(&self) -> String {
        match (self.controller_fault, self.fault) {
            (0, g) => format!("Robotiq fault 0x{g:02X}: {}", fault_name(g)),
            (k, 0) => format!("Robotiq controller fault kFLT 0x{k:X} (gFLT clear): see the controller's manual"),
            (k, g) => format!("Robotiq fault 0x{g:02X}: {}; controller fault kFLT 0x{k:X}", fault_name(g)),
        }
    }

    /// The grasp as the runtime reports it (`GRASP_*`).
    pub fn grasp(&self) -> u32 {
        if !self.ready() {
            return ipc_schema::GRASP_UNKNOWN;
        }
        match self.object {
            0 if self.going => ipc_schema::GRASP_MOVING,
            0 => ipc_schema::GRASP_UNKNOWN,
            1 => ipc_schema::GRASP_BLOCKED_OPENING,
            2 => ipc_schema::GRASP_HOLDING,
            _ => ipc_schema::GRASP_AT_TARGET,
        }
    }
}

/// How a fault stops the gripper (the 2F-85 manual's classes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultClass {
    /// No fault, or a priority fault (0x05, 0x07: an action waits for the activation).
    None,
    /// 0x08 (too hot) and 0x09 (no communication for 1 s): the gripper goes on by itself once
    /// the cause is gone; no reset.
    Minor,
    /// 0x0A to 0x0F, or a controller fault (`kFLT`): only a reset (rACT 0, then 1) ends it.
    Major,
}

/// The manual's meaning of a `gFLT` code, in our words.
pub fn fault_name(code: u8) -> &'static str {
    match code {
        0x00 => "no fault",
        0x05 => "action delayed: the activation must finish first",
        0x07 => "the activation bit must be set before an action",
        0x08 => "maximum operating temperature exceeded: it goes on once cooled down",
        0x09 => "no communication for at least 1 s: it goes on once requests arrive again",
        0x0A => "supply voltage under the minimum",
        0x0B => "automatic release in progress",
        0x0C => "internal fault: contact support",
        0x0D => "activation fault: check that nothing blocks the fingers, then reactivate",
        0x0E => "overcurrent: the motor current was too high",
        0x0F => "automatic release completed",
        _ => "unknown fault code",
    }
}

/// Position counts ↔ opening. `closed` is the count at which the pads meet (the map is linear
/// from 0, fully open, to it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scale {
    pub closed: u8,
}

impl Scale {
    /// Fraction open (1 fully open … 0 closed) of a position count.
    pub fn fraction_open(&self, position: u8) -> f64 {
        let c = f64::from(self.closed);
        ((c - f64::from(position).min(c)) / c).clamp(0.0, 1.0)
    }

    /// The position count for a fraction open (clamped to 0..=1; NaN counts as closed).
    pub fn position(&self, fraction_open: f64) -> u8 {
        let f = if fraction_open.is_nan() { 0.0 } else { fraction_open.clamp(0.0, 1.0) };
        (f64::from(self.closed) * (1.0 - f)).round() as u8
    }
}

/// Builds the two requests the driver sends and checks their answers (rmodbus does the
/// framing and the CRC).
pub struct Frames {
    slave: u8,
}

impl Frames {
    pub fn new(slave: u8) -> Self {
        Self { slave }
    }

    /// Write the three request registers (function 16). The answer is 8 bytes.
    pub fn write(&self, c: &Command) -> (ModbusRequest, Vec<u8>) {
        let mut req = ModbusRequest::new(self.slave, ModbusProto::Rtu);
        let mut frame = Vec::with_capacity(15);
        // Three registers always fit a frame.
        let _ = req.generate_set_holdings_bulk(OUTPUT_REGISTER, &c.registers(), &mut frame);
        (req, frame)
    }

    /// Read `count` status registers (function 3). The answer is 5 + 2 × count bytes.
    pub fn read_status(&self, count: u16) -> (ModbusRequest, Vec<u8>) {
        let mut req = ModbusRequest::new(self.slave, ModbusProto::Rtu);
        let mut frame = Vec::with_capacity(8);
        let _ = req.generate_get_holdings(INPUT_REGISTER, count, &mut frame);
        (req, frame)
    }
}

/// Length of the whole answer once its first three bytes are in (an exception answer is 5
/// bytes).
pub fn answer_len(head: &[u8]) -> Result<usize, ErrorKind> {
    rmodbus::guess_response_frame_len(head, ModbusProto::Rtu).map(usize::from)
}

/// Checks an answer to a write (slave, function, CRC, no exception).
pub fn parse_write(req: &ModbusRequest, answer: &[u8]) -> Result<(), ErrorKind> {
    req.parse_ok(answer)
}

/// Checks an answer to a status read and decodes it.
pub fn parse_status(req: &ModbusRequest, answer: &[u8]) -> Result<Status, ErrorKind> {
    let mut regs = Vec::with_capacity(3);
    req.parse_u16(answer, &mut regs)?;
    Ok(Status::from_registers(&regs))
}

/// Words for an rmodbus error.
pub fn describe(e: ErrorKind) -> String {
    match e {
        ErrorKind::FrameCRCError => "the answer's CRC does not match (noise on the line, or a wrong baud rate)".into(),
        ErrorKind::FrameBroken => "the answer is not a frame of this request (wrong slave id or function)".into(),
        other => format!("Modbus error: {other:?}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        s.split_whitespace().map(|b| u8::from_str_radix(b, 16).unwrap()).collect()
    }

    /// The worked examples of the 2F-85 manual (Modbus RTU section), byte for byte, CRC
    /// included: what we send must be what the manual sends, and what the manual's gripper
    /// answers must decode to what the manual says it means.
    #[test]
    fn the_manuals_frames_byte_for_byte() {
        let f = Frames::new(9);
        // Clear rACT, then set it (activation).
        assert_eq!(f.write(&Command::default()).1, hex("09 10 03 E8 00 03 06 00 00 00 00 00 00 73 30"));
        let activate = Command { activate: true, ..Command::default() };
        let (req, frame) = f.write(&activate);
        assert_eq!(frame, hex("09 10 03 E8 00 03 06 01 00 00 00 00 00 72 E1"));
        parse_write(&req, &hex("09 10 03 E8 00 03 01 30")).unwrap();
        // Poll the first status register until the activation has finished.
        let (req, frame) = f.read_status(1);
        assert_eq!(frame, hex("09 03 07 D0 00 01 85 CF"));
        let activating = parse_status(&req, &hex("09 03 02 11 00 55 D5")).unwrap();
        assert!(activating.activated && activating.activation == 1 && !activating.ready());
        let ready = parse_status(&req, &hex("09 03 02 31 00 4C 15")).unwrap();
        assert!(ready.ready() && ready.fault == 0);
        // Close at full speed and force.
        let close = Command { activate: true, go: true, position: 0xFF, speed: 0xFF, force: 0xFF };
        let (req, frame) = f.write(&close);
        assert_eq!(frame, hex("09 10 03 E8 00 03 06 09 00 00 FF FF FF 42 29"));
        parse_write(&req, &hex("09 10 03 E8 00 03 01 30")).unwrap();
        // Poll all three status registers: moving, then stopped on an object.
        let (req, frame) = f.read_status(3);
        assert_eq!(frame, hex("09 03 07 D0 00 03 04 0E"));
        let moving = parse_status(&req, &hex("09 03 06 39 00 00 FF 0E 0A F7 8B")).unwrap();
        assert_eq!((moving.object, moving.requested, moving.position, moving.current_ma), (0, 0xFF, 0x0E, 100));
        assert_eq!(moving.grasp(), ipc_schema::GRASP_MOVING);
        let held = parse_status(&req, &hex("09 03 06 B9 00 00 FF BD 00 1D 7C")).unwrap();
        assert_eq!((held.object, held.position), (2, 0xBD));
        assert_eq!(held.grasp(), ipc_schema::GRASP_HOLDING);
        // Open at full speed and force.
        let open = Command { position: 0, ..close };
        assert_eq!(f.write(&open).1, hex("09 10 03 E8 00 03 06 09 00 00 00 FF FF 72 19"));
    }

    #[test]
    fn bad_answers_are_named() {
        let f = Frames::new(9);
        let (req, _) = f.read_status(3);
        // One bit flipped in the CRC.
        assert_eq!(parse_status(&req, &hex("09 03 06 B9 00 00 FF BD 00 1D 7D")), Err(ErrorKind::FrameCRCError));
        // Another slave's answer.
        let mut other = hex("0A 03 06 B9 00 00 FF BD 00");
        let crc = crc16(&other);
        other.extend(crc.to_le_bytes());
        assert!(parse_status(&req, &other).is_err());
        // An exception answer (illegal data address) of the right slave.
        let mut exc = hex("09 83 02");
        let crc = crc16(&exc);
        exc.extend(crc.to_le_bytes());
        assert_eq!(answer_len(&exc[..3]), Ok(5));
        assert_eq!(parse_status(&req, &exc), Err(ErrorKind::IllegalDataAddress));
        assert_eq!(answer_len(&hex("09 03 06")), Ok(11));
        assert_eq!(answer_len(&hex("09 10 03")), Ok(8));
    }

    /// CRC-16/MODBUS written out here, independent of rmodbus's.
    fn crc16(b: &[u8]) -> u16 {
        let mut c = 0xFFFFu16;
        for &x in b {
            c ^= u16::from(x);
            for _ in 0..8 {
                c = if c & 1 != 0 { (c >> 1) ^ 0xA001 } else { c >> 1 };
            }
        }
        c
    }

    /// Every code's class as the manual gives it: 0x08 and 0x09 are minor (no reset), 0x0A to
    /// 0x0F major (a reset), 0x05 and 0x07 only delay an action; any kFLT is major.
    #[test]
    fn fault_classes_follow_the_manual() {
        let class = |byte: u16| Status::from_registers(&[0x3100, byte << 8, 0]).fault_class();
        for g in 0..=0x0Fu16 {
            let want = match g {
                0x08 | 0x09 => FaultClass::Minor,
                0x0A..=0x0F => FaultClass::Major,
                _ => FaultClass::None,
            };
            assert_eq!(class(g), want, "gFLT 0x{g:02X}");
        }
        // kFLT alone: a fault, published as a non-zero code that names it.
        let k = Status::from_registers(&[0x3100, 0x3000, 0]);
        assert_eq!((k.fault, k.controller_fault), (0, 3));
        assert_eq!(k.fault_class(), FaultClass::Major);
        assert_eq!(k.fault_code(), 0x30);
        assert!(k.fault_text().contains("kFLT 0x3"), "{}", k.fault_text());
        let both = Status::from_registers(&[0x3100, 0x3E00, 0]);
        assert_eq!(both.fault_code(), 0x3E);
        assert!(both.fault_text().contains("overcurrent") && both.fault_text().contains("kFLT"));
    }

    #[test]
    fn faults_and_scale() {
        let s = Status::from_registers(&[0x3100, 0x0E00, 0x0000]);
        assert!(s.fault_class() == FaultClass::Major && s.fault == 0x0E);
        assert!(fault_name(0x0E).contains("overcurrent"));
        assert!(s.fault_text().starts_with("Robotiq fault 0x0E: overcurrent"));
        assert_eq!(Status::from_registers(&[0x3100, 0x0700, 0]).fault_class(), FaultClass::None);
        let k = Scale { closed: 230 };
        assert_eq!(k.position(1.0), 0);
        assert_eq!(k.position(0.0), 230);
        assert_eq!(k.position(f64::NAN), 230);
        assert_eq!(k.fraction_open(255), 0.0);
        assert!((k.fraction_open(k.position(0.3)) - 0.3).abs() < 1.0 / 230.0);
    }
}
