//! Cassettes: a real model's answers recorded once (`--llm record:<endpoint.toml>`) and
//! replayed without a network (`--llm replay:<cassette>`).
//!
//! Each request is reduced to a canonical form ([`canonical`]) that does not depend on the wire
//! format: model, sampling parameters that change the answer (temperature, max_tokens), system
//! prompt and messages with their roles; texts are represented by their SHA-256, images by the
//! SHA-256 of their decoded pixels (as RGBA, with width, height and bit depth), so re-encoding a
//! PNG does not change the request. The key is the SHA-256 of that form written as JSON with
//! sorted keys and no whitespace.
//!
//! The file is JSON Lines: a header (`{"r2g_cassette": 1, "endpoint": {...}}`), then one entry
//! per answer: `{"key", "request", "texts", "response": {"text", "usage", "raw", "attempts",
//! "wall_s"}}`, where `texts` holds the texts (by hash) not written by an earlier line, so the
//! system prompt and the history are stored once. Each entry is appended with one write and
//! synced, so a killed run keeps every finished answer.
//!
//! Entry points: [`Recorder::create`], [`Player::open`], [`canonical`].

use std::collections::{HashMap, HashSet};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use sha2::{Digest, Sha256};

use crate::llm::{Completion, EndpointConfig, Message, Part, Usage};

/// The cassette format written and read here.
pub const FORMAT: u64 = 1;

/// What `--llm record:` and `--llm replay:` attach to an endpoint (it appears in the run's
/// `config.json` under `endpoint.cassette`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CassetteSpec {
    pub mode: CassetteMode,
    pub path: PathBuf,
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum CassetteMode {
    Record,
    Replay,
}

#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CassetteError {
    #[error("cassette {path}: {detail}")]
    Io { path: PathBuf, detail: String },
    #[error("cassette {path}, line {line}: {detail}")]
    Malformed { path: PathBuf, line: usize, detail: String },
    #[error("message {message}, part {part}: the image is not a decodable PNG ({detail})")]
    Image { message: usize, part: usize, detail: String },
    #[error("request {key} is not in the cassette {path} ({entries} recorded answers): {nearest}")]
    Miss { key: String, path: PathBuf, entries: usize, nearest: String },
}

/// A request in canonical form, its key and the texts its digests stand for.
#[derive(Debug, Clone)]
pub struct Canonical {
    pub request: Value,
    pub key: String,
    pub texts: HashMap<String, String>,
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// JSON with object keys sorted at every level and no whitespace.
pub fn canonical_json(v: &Value) -> String {
    fn write(v: &Value, out: &mut String) {
        match v {
            Value::Object(m) => {
                let mut keys: Vec<&String> = m.keys().collect();
                keys.sort();
                out.push('{');
                for (i, k) in keys.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    out.push_str(&Value::String((*k).clone()).to_string());
                    out.push(':');
                    write(&m[k.as_str()], out);
                }
                out.push('}');
            }
            Value::Array(a) => {
                out.push('[');
                for (i, x) in a.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    write(x, out);
                }
                out.push(']');
            }
            scalar => out.push_str(&scalar.to_string()),
        }
    }
    let mut out = String::new();
    write(v, &mut out);
    out
}

fn key_of(request: &Value) -> String {
    sha256_hex(canonical_json(request).as_bytes())
}

/// The decoded pixels of a PNG, as RGBA at the image's bit depth (palettes and low bit depths
/// expanded, grey replicated, a missing alpha set to opaque): `{width, height, depth, rgba_sha256}`.
pub fn pixel_digest(png_bytes: &[u8]) -> Result<Value, String> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(png_bytes));
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let size = reader.output_buffer_size().ok_or("the image is too large to decode")?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    let bytes_per_sample = match info.bit_depth {
        png::BitDepth::Sixteen => 2,
        _ => 1,
    };
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err("a palette image was not expanded".into()),
    };
    let opaque = vec![0xffu8; bytes_per_sample];
    let mut h = Sha256::new();
    h.update(info.width.to_le_bytes());
    h.update(info.height.to_le_bytes());
    h.update([bytes_per_sample as u8 * 8]);
    let pixel = channels * bytes_per_sample;
    for row in buf.chunks_exact(info.line_size).take(info.height as usize) {
        for px in row.chunks_exact(pixel).take(info.width as usize) {
            let s = |i: usize| &px[i * bytes_per_sample..(i + 1) * bytes_per_sample];
            let (r, g, b, a) = match channels {
                1 => (s(0), s(0), s(0), &opaque[..]),
                2 => (s(0), s(0), s(0), s(1)),
                3 => (s(0), s(1), s(2), &opaque[..]),
                _ => (s(0), s(1), s(2), s(3)),
            };
            for c in [r, g, b, a] {
                h.update(c);
            }
        }
    }
    Ok(json!({"width": info.width, "height": info.height, "depth": bytes_per_sample * 8,
              "rgba_sha256": hex(&h.finalize())}))
}

/// The canonical form of a request and its key.
pub fn canonical(
    model: &str,
    temperature: f64,
    max_tokens: u32,
    system: &str,
    messages: &[Message],
) -> Result<Canonical, CassetteError> {
    let mut texts = HashMap::new();
    let mut text = |t: &str| {
        let d = sha256_hex(t.as_bytes());
        texts.insert(d.clone(), t.to_string());
        json!({ "text": d })
    };
    let system = text(system);
    let mut msgs = Vec::with_capacity(messages.len());
    for (i, m) in messages.iter().enumerate() {
        let mut parts = Vec::with_capacity(m.parts.len());
        for (j, p) in m.parts.iter().enumerate() {
            parts.push(match p {
                Part::Text(t) => text(t),
                Part::Png(png) => json!({"image": pixel_digest(png)
                    .map_err(|detail| CassetteError::Image { message: i, part: j, detail })?}),
            });
        }
        msgs.push(json!({"role": m.role, "parts": parts}));
    }
    let request = json!({"model": model, "temperature": temperature, "max_tokens": max_tokens,
                         "system": system, "messages": msgs});
    Ok(Canonical { key: key_of(&request), request, texts })
}

/// The endpoint fields a cassette's header keeps (no key, no timeouts).
fn header(endpoint: &EndpointConfig) -> Value {
    json!({"r2g_cassette": FORMAT, "endpoint": {
        "provider": endpoint.provider, "base_url": endpoint.base_url, "model": endpoint.model,
        "temperature": endpoint.temperature, "max_tokens": endpoint.max_tokens}})
}

/// Appends each answer of a live endpoint to a new cassette.
pub struct Recorder {
    path: PathBuf,
    state: Mutex<(File, HashSet<String>)>,
}

impl Recorder {
    /// Starts a new cassette at `path` (replacing one there) with the endpoint's header.
    pub fn create(path: &Path, endpoint: &EndpointConfig) -> Result<Self, CassetteError> {
        let io = |e: std::io::Error| CassetteError::Io { path: path.to_path_buf(), detail: e.to_string() };
        let tmp = path.with_extension("partial");
        std::fs::write(&tmp, format!("{}\n", header(endpoint))).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)?;
        let file = std::fs::OpenOptions::new().append(true).open(path).map_err(io)?;
        Ok(Self { path: path.to_path_buf(), state: Mutex::new((file, HashSet::new())) })
    }

    /// One answer, as one line written with one call and synced.
    pub fn append(&self, c: &Canonical, out: &Completion) -> Result<(), CassetteError> {
        let io = |e: std::io::Error| CassetteError::Io { path: self.path.clone(), detail: e.to_string() };
        let mut state = self
            .state
            .lock()
            .map_err(|_| CassetteError::Io { path: self.path.clone(), detail: "an earlier write panicked".into() })?;
        let (file, written) = &mut *state;
        let mut new: Vec<(&String, &String)> = c.texts.iter().filter(|(d, _)| !written.contains(*d)).collect();
        new.sort();
        let texts: serde_json::Map<String, Value> = new.iter().map(|(d, t)| ((*d).clone(), json!(t))).collect();
        let entry = json!({"key": c.key, "request": c.request, "texts": texts, "response": {
            "text": out.text, "usage": out.usage, "raw": out.raw, "attempts": out.attempts, "wall_s": out.wall_s}});
        let mut line = entry.to_string();
        line.push('\n');
        file.write_all(line.as_bytes()).map_err(io)?;
        file.sync_data().map_err(io)?;
        written.extend(new.into_iter().map(|(d, _)| d.clone()));
        Ok(())
    }
}

/// A recorded answer.
#[derive(Debug, Clone, Deserialize)]
pub struct Recorded {
    pub text: String,
    pub usage: Usage,
    #[serde(default)]
    pub raw: Value,
    #[serde(default)]
    pub attempts: u32,
    #[serde(default)]
    pub wall_s: f64,
}

/// A cassette read whole, answering requests by key.
pub struct Player {
    pub path: PathBuf,
    /// The endpoint that was recorded (model and sampling parameters make up the key).
    pub endpoint: EndpointConfig,
    answers: HashMap<String, Vec<Recorded>>,
    /// Every recorded request in file order, for saying how a missing one differs.
    requests: Vec<Value>,
    texts: HashMap<String, String>,
    /// How many times each key has been answered (a key recorded twice is answered in order).
    served: Mutex<HashMap<String, usize>>,
}

impl Player {
    pub fn open(path: &Path) -> Result<Self, CassetteError> {
        let bad = |line: usize, detail: String| CassetteError::Malformed { path: path.to_path_buf(), line, detail };
        let data = std::fs::read_to_string(path)
            .map_err(|e| CassetteError::Io { path: path.to_path_buf(), detail: e.to_string() })?;
        if !data.is_empty() && !data.ends_with('\n') {
            let line = data.lines().count();
            return Err(bad(
                line,
                "the last line is incomplete (a run killed while writing it?); remove it to use the answers before it"
                    .into(),
            ));
        }
        let mut lines = data.lines().enumerate().map(|(i, l)| (i + 1, l));
        let (_, head) = lines.next().ok_or_else(|| bad(1, "the file is empty".into()))?;
        let head: Value = serde_json::from_str(head).map_err(|e| bad(1, format!("the header is not JSON: {e}")))?;
        if head["r2g_cassette"] != FORMAT {
            return Err(bad(
                1,
                format!("not a cassette of format {FORMAT} (the header needs \"r2g_cassette\": {FORMAT})"),
            ));
        }
        let mut endpoint: EndpointConfig = serde_json::from_value(head["endpoint"].clone())
            .map_err(|e| bad(1, format!("the header's endpoint: {e}")))?;
        endpoint.check().map_err(|e| bad(1, format!("the header's endpoint: {e:#}")))?;
        endpoint.cassette = Some(CassetteSpec { mode: CassetteMode::Replay, path: path.to_path_buf() });
        let mut player = Self {
            path: path.to_path_buf(),
            endpoint,
            answers: HashMap::new(),
            requests: Vec::new(),
            texts: HashMap::new(),
            served: Mutex::new(HashMap::new()),
        };
        for (n, line) in lines {
            let v: Value = serde_json::from_str(line).map_err(|e| bad(n, format!("not JSON: {e}")))?;
            let key = v["key"].as_str().ok_or_else(|| bad(n, "no \"key\" string".into()))?.to_string();
            let request = v.get("request").cloned().ok_or_else(|| bad(n, "no \"request\"".into()))?;
            if key_of(&request) != key {
                return Err(bad(n, format!("the request does not hash to its key {key} (edited by hand?)")));
            }
            for (d, t) in v["texts"].as_object().into_iter().flatten() {
                let t = t.as_str().ok_or_else(|| bad(n, format!("text {d} is not a string")))?;
                if sha256_hex(t.as_bytes()) != *d {
                    return Err(bad(n, format!("text {d} does not hash to its name")));
                }
                player.texts.insert(d.clone(), t.to_string());
            }
            if let Some(d) = digests(&request).into_iter().find(|d| !player.texts.contains_key(*d)) {
                return Err(bad(n, format!("the request refers to text {d}, which no line up to here holds")));
            }
            let r: Recorded =
                serde_json::from_value(v["response"].clone()).map_err(|e| bad(n, format!("the response: {e}")))?;
            player.answers.entry(key).or_default().push(r);
            player.requests.push(request);
        }
        Ok(player)
    }

    /// Answers recorded so far.
    pub fn len(&self) -> usize {
        self.requests.len()
    }

    pub fn is_empty(&self) -> bool {
        self.requests.is_empty()
    }

    /// The recorded answer to this request; a request not recorded is an error that names its
    /// key and how the closest recorded request differs.
    pub fn answer(&self, c: &Canonical) -> Result<Recorded, CassetteError> {
        let Some(list) = self.answers.get(&c.key) else {
            return Err(CassetteError::Miss {
                key: c.key.clone(),
                path: self.path.clone(),
                entries: self.requests.len(),
                nearest: self.nearest(c),
            });
        };
        let mut served = self.served.lock().unwrap_or_else(|p| p.into_inner());
        let i = served.entry(c.key.clone()).or_insert(0);
        // Asked once more than it was recorded: not in the cassette either (never a repeat).
        let Some(r) = list.get(*i).cloned() else {
            return Err(CassetteError::Miss {
                key: c.key.clone(),
                path: self.path.clone(),
                entries: self.requests.len(),
                nearest: format!(
                    "this exact request was recorded {} time(s), and each of its answers has been served already",
                    list.len()
                ),
            });
        };
        *i += 1;
        Ok(r)
    }

    /// How the recorded request sharing the longest prefix of messages with `c` differs.
    fn nearest(&self, c: &Canonical) -> String {
        let msgs = |r: &Value| r["messages"].as_array().map_or(0, Vec::len);
        let text_of = |v: Option<&Value>, texts: &HashMap<String, String>| {
            v.and_then(|v| v["text"].as_str()).and_then(|d| texts.get(d)).cloned()
        };
        let common = |a: &str, b: &str| a.chars().zip(b.chars()).take_while(|(x, y)| x == y).count();
        // Closest: the first difference latest in the messages (message, part, character),
        // then the same number of messages, then the same model, parameters and system prompt;
        // the earliest answer among equals.
        let Some((i, _, (path, was, is))) = self
            .requests
            .iter()
            .enumerate()
            .filter_map(|(i, r)| first_difference(r, &c.request, String::new()).map(|d| (i, r, d)))
            .max_by_key(|(i, r, (_, was, is))| {
                let equal_start = |a: Option<&Vec<Value>>, b: Option<&Vec<Value>>| {
                    a.zip(b).map_or(0, |(a, b)| a.iter().zip(b).take_while(|(x, y)| x == y).count())
                };
                let same = equal_start(r["messages"].as_array(), c.request["messages"].as_array());
                let parts = |v: &Value| v["messages"][same]["parts"].as_array().cloned();
                let same_parts = equal_start(parts(r).as_ref(), parts(&c.request).as_ref());
                let head = ["model", "temperature", "max_tokens", "system"].iter().filter(|k| r[**k] == c.request[**k]);
                let chars = match (text_of(*was, &self.texts), text_of(*is, &c.texts)) {
                    (Some(a), Some(b)) => common(&a, &b),
                    _ => 0,
                };
                (same, same_parts, chars, msgs(r) == msgs(&c.request), head.count(), usize::MAX - i)
            })
        else {
            // (An equal request has the same key, so only an empty cassette gets here.)
            return "the cassette holds no answers".into();
        };
        let head = format!("closest is answer {} (line {}); {path} differs", i + 1, i + 2);
        match (text_of(was, &self.texts), text_of(is, &c.texts)) {
            (Some(a), Some(b)) => {
                let at = common(&a, &b);
                let around = |s: &str| excerpt(&s.chars().skip(at.saturating_sub(20)).collect::<String>(), 80);
                format!("{head} from character {at}: recorded {:?}, now {:?}", around(&a), around(&b))
            }
            _ => {
                let show = |v: Option<&Value>| v.map_or_else(|| "(absent)".to_string(), canonical_json);
                format!("{head}: recorded {}, now {}", show(was), show(is))
            }
        }
    }
}

fn excerpt(s: &str, n: usize) -> String {
    let mut e: String = s.chars().take(n).collect();
    if s.chars().count() > n {
        e.push('…');
    }
    e
}

/// Text digests a canonical request refers to.
fn digests(v: &Value) -> Vec<&str> {
    let mut out = Vec::new();
    fn walk<'a>(v: &'a Value, out: &mut Vec<&'a str>) {
        match v {
            Value::Object(m) => {
                if let Some(Value::String(d)) = m.get("text") {
                    out.push(d);
                }
                m.values().for_each(|x| walk(x, out));
            }
            Value::Array(a) => a.iter().for_each(|x| walk(x, out)),
            _ => {}
        }
    }
    walk(v, &mut out);
    out
}

/// The first place two canonical requests differ: its path (`messages[3].parts[0]`) and the
/// values there. Stops at a part or a top-level field, whichever comes first.
fn first_difference<'a>(
    a: &'a Value,
    b: &'a Value,
    at: String,
) -> Option<(String, Option<&'a Value>, Option<&'a Value>)> {
    if a == b {
        return None;
    }
    let leaf = (at.ends_with(']') && at.contains(".parts[")) || (!at.is_empty() && !at.starts_with("messages"));
    match (a, b) {
        (Value::Object(x), Value::Object(y)) if !leaf => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|k| {
                let p = if at.is_empty() { k.clone() } else { format!("{at}.{k}") };
                match (x.get(k), y.get(k)) {
                    (Some(p1), Some(p2)) => first_difference(p1, p2, p),
                    (u, v) => Some((p, u, v)),
                }
            })
        }
        (Value::Array(x), Value::Array(y)) if !leaf => {
            (0..x.len().max(y.len())).find_map(|i| match (x.get(i), y.get(i)) {
                (Some(p1), Some(p2)) => first_difference(p1, p2, format!("{at}[{i}]")),
                (u, v) => Some((format!("{at}[{i}]"), u, v)),
            })
        }
        _ => Some((at, Some(a), Some(b))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::llm::Role;

    fn png_of(rgba: &[[u8; 4]], w: u32, h: u32, color: png::ColorType, compression: png::Compression) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut e = png::Encoder::new(&mut out, w, h);
            e.set_color(color);
            e.set_compression(compression);
            let data: Vec<u8> = match color {
                png::ColorType::Rgb => rgba.iter().flat_map(|p| [p[0], p[1], p[2]]).collect(),
                _ => rgba.iter().flat_map(|p| *p).collect(),
            };
            let mut w = e.write_header().expect("header");
            w.write_image_data(&data).expect("pixels");
        }
        out
    }

    fn pixels() -> Vec<[u8; 4]> {
        (0..12u8).map(|i| [i * 20, 255 - i * 7, i * 3, 255]).collect()
    }

    fn request(png: Vec<u8>, feedback: &str) -> Vec<Message> {
        vec![
            Message { role: Role::User, parts: vec![Part::Text("observe".into()), Part::Png(png.clone())] },
            Message::text(Role::Assistant, "<stop>looked</stop>"),
            Message { role: Role::User, parts: vec![Part::Text(feedback.into()), Part::Png(png)] },
        ]
    }

    fn endpoint() -> EndpointConfig {
        EndpointConfig {
            provider: "openai".into(),
            base_url: "http://127.0.0.1:1".into(),
            model: "m".into(),
            api_key_env: None,
            temperature: 0.0,
            max_tokens: 64,
            timeout_s: 5.0,
            retries: 0,
            cassette: None,
        }
    }

    fn completion(text: &str) -> Completion {
        Completion {
            text: text.into(),
            usage: Usage { input: 120, cached: 100, output: 7, reasoning: Some(2), raw: json!({"prompt_tokens": 120}) },
            attempts: 1,
            wall_s: 0.5,
            raw: json!({"id": "x"}),
            truncated: false,
        }
    }

    fn key(msgs: &[Message]) -> String {
        canonical("m", 0.0, 64, "sys", msgs).expect("canonical").key
    }

    #[test]
    fn a_re_encoded_png_with_the_same_pixels_has_the_same_key() {
        let p = pixels();
        let rgb_fast = png_of(&p, 4, 3, png::ColorType::Rgb, png::Compression::Fast);
        let rgba_best = png_of(&p, 4, 3, png::ColorType::Rgba, png::Compression::High);
        assert_ne!(rgb_fast, rgba_best, "the encodings must differ for this test to mean anything");
        assert_eq!(key(&request(rgb_fast.clone(), "f")), key(&request(rgba_best, "f")));
        let mut q = p.clone();
        q[5][1] ^= 1;
        let one_pixel_off = png_of(&q, 4, 3, png::ColorType::Rgb, png::Compression::Fast);
        assert_ne!(key(&request(rgb_fast.clone(), "f")), key(&request(one_pixel_off, "f")));
        // Same bytes, other shape: a different image.
        let tall = png_of(&p, 3, 4, png::ColorType::Rgb, png::Compression::Fast);
        assert_ne!(key(&request(rgb_fast.clone(), "f")), key(&request(tall, "f")));
        // The text, the role, the model and the sampling parameters are part of the key.
        let base = canonical("m", 0.0, 64, "sys", &request(rgb_fast.clone(), "f")).expect("c").key;
        for other in [
            canonical("m", 0.0, 64, "sys", &request(rgb_fast.clone(), "g")),
            canonical("m2", 0.0, 64, "sys", &request(rgb_fast.clone(), "f")),
            canonical("m", 0.5, 64, "sys", &request(rgb_fast.clone(), "f")),
            canonical("m", 0.0, 65, "sys", &request(rgb_fast.clone(), "f")),
            canonical("m", 0.0, 64, "sys2", &request(rgb_fast.clone(), "f")),
        ] {
            assert_ne!(other.expect("c").key, base);
        }
    }

    #[test]
    fn an_undecodable_image_names_its_message_and_part() {
        let mut msgs = request(png_of(&pixels(), 4, 3, png::ColorType::Rgb, png::Compression::Fast), "f");
        msgs[2].parts[1] = Part::Png(b"\x89PNG\r\n\x1a\nnot really".to_vec());
        match canonical("m", 0.0, 64, "sys", &msgs) {
            Err(CassetteError::Image { message: 2, part: 1, .. }) => {}
            other => panic!("expected an image error, got {other:?}"),
        }
    }

    fn recorded(dir: &Path) -> (PathBuf, Vec<u8>) {
        let png = png_of(&pixels(), 4, 3, png::ColorType::Rgb, png::Compression::Fast);
        let path = dir.join("c.jsonl");
        let rec = Recorder::create(&path, &endpoint()).expect("create");
        for (fb, answer) in [("feedback one", "first"), ("feedback two", "second")] {
            let c = canonical("m", 0.0, 64, "sys", &request(png.clone(), fb)).expect("c");
            rec.append(&c, &completion(answer)).expect("append");
        }
        (path, png)
    }

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("r2g-cassette-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).expect("tmp");
        d
    }

    #[test]
    fn answers_come_back_by_key_whatever_the_key_order_and_whitespace_of_the_file() {
        let dir = tmp("order");
        let (path, png) = recorded(&dir);
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text.matches("\"sys\"").count(), 1, "the system prompt is stored once: {text}");
        // Rewrite every line pretty-printed on one line with its keys reversed.
        fn reversed(v: &Value) -> String {
            match v {
                Value::Object(m) => {
                    let mut keys: Vec<&String> = m.keys().collect();
                    keys.sort();
                    keys.reverse();
                    let inner: Vec<String> =
                        keys.iter().map(|k| format!(" {} :  {}", json!(k), reversed(&m[*k]))).collect();
                    format!("{{ {} }}", inner.join(" , "))
                }
                Value::Array(a) => format!("[ {} ]", a.iter().map(reversed).collect::<Vec<_>>().join(" ,  ")),
                s => s.to_string(),
            }
        }
        let shuffled: String = text.lines().map(|l| reversed(&serde_json::from_str(l).expect("json")) + "\n").collect();
        assert_ne!(shuffled, text);
        std::fs::write(&path, shuffled).expect("write");
        let p = Player::open(&path).expect("open");
        assert_eq!(p.len(), 2);
        assert_eq!(p.endpoint.model, "m");
        let c = canonical("m", 0.0, 64, "sys", &request(png.clone(), "feedback two")).expect("c");
        let r = p.answer(&c).expect("recorded");
        assert_eq!(r.text, "second");
        assert_eq!(r.usage, completion("x").usage, "usage as recorded");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_changed_request_fails_with_its_key_and_the_differing_part() {
        let dir = tmp("miss");
        let (path, png) = recorded(&dir);
        let p = Player::open(&path).expect("open");
        let c = canonical("m", 0.0, 64, "sys", &request(png.clone(), "feedback twx")).expect("c");
        let e = p.answer(&c).expect_err("not recorded").to_string();
        assert!(e.contains(&c.key), "{e}");
        assert!(e.contains("messages[2].parts[0]") && e.contains("character 11"), "{e}");
        assert!(e.contains("\"feedback two\"") && e.contains("\"feedback twx\""), "{e}");
        // Another image: the differing part is the image, shown by its digest.
        let other = png_of(&pixels()[..6], 3, 2, png::ColorType::Rgb, png::Compression::Fast);
        let mut msgs = request(png, "feedback two");
        msgs[2].parts[1] = Part::Png(other);
        let e = p.answer(&canonical("m", 0.0, 64, "sys", &msgs).expect("c")).expect_err("not recorded").to_string();
        assert!(e.contains("messages[2].parts[1] differs") && e.contains("\"width\":3"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn truncated_or_tampered_cassettes_are_refused_with_the_line() {
        let dir = tmp("bad");
        let (path, _) = recorded(&dir);
        let text = std::fs::read_to_string(&path).expect("read");
        let cases: Vec<(String, &str)> = vec![
            (text[..text.len() - 30].to_string(), "line 3: the last line is incomplete"),
            (text.replacen("first", "other", 1), ""),
            (text.replacen("\"max_tokens\":64", "\"max_tokens\":65", 2), "does not hash to its key"),
            (text.replacen("feedback one", "feedback 0ne", 1), "does not hash to its name"),
            (String::new(), "line 1: the file is empty"),
            ("{\"hello\": 1}\n".into(), "line 1: not a cassette"),
            (format!("{}\n{{\"key\": 3}}\n", text.lines().next().expect("head")), "line 2: no \"key\" string"),
        ];
        for (body, want) in cases {
            std::fs::write(&path, &body).expect("write");
            match Player::open(&path) {
                Ok(_) if want.is_empty() => {} // an edited answer is still an answer
                Ok(_) => panic!("accepted: {want}"),
                Err(e) => assert!(!want.is_empty() && e.to_string().contains(want), "{e} (wanted {want:?})"),
            }
        }
        // A line that drops the text table: the request refers to texts no line holds.
        let mut lines: Vec<Value> = text.lines().map(|l| serde_json::from_str(l).expect("json")).collect();
        lines[1]["texts"] = json!({});
        std::fs::write(&path, lines.iter().map(|l| format!("{l}\n")).collect::<String>()).expect("write");
        let e = Player::open(&path).err().expect("refused").to_string();
        assert!(e.contains("line 2") && e.contains("no line up to here holds"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_key_recorded_twice_is_answered_in_recorded_order() {
        let dir = tmp("twice");
        let path = dir.join("c.jsonl");
        let rec = Recorder::create(&path, &endpoint()).expect("create");
        let c = canonical("m", 0.0, 64, "sys", &[Message::text(Role::User, "hi")]).expect("c");
        rec.append(&c, &completion("one")).expect("append");
        rec.append(&c, &completion("two")).expect("append");
        let p = Player::open(&path).expect("open");
        let got: Vec<String> = (0..2).map(|_| p.answer(&c).expect("answer").text).collect();
        assert_eq!(got, ["one", "two"]);
        // A third ask was never recorded: it fails loudly, never repeats the last answer.
        let e = p.answer(&c).expect_err("a third ask is a miss").to_string();
        assert!(e.contains("recorded 2 time(s)") && e.contains("served already"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
