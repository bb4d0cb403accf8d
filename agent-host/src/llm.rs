//! LLM endpoints: OpenAI-compatible chat completions (OpenAI, vLLM, Ollama, llama.cpp,
//! LiteLLM) and Anthropic Messages, both with PNG image input, over blocking HTTPS with bounded
//! time, bounded body size and bounded retries. Usage is normalised per response.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use base64::Engine as _;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::cassette::{self, CassetteError, CassetteMode, CassetteSpec, Player, Recorder};

/// One endpoint, as its TOML file describes it.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct EndpointConfig {
    /// "openai" (any OpenAI-compatible chat-completions server) or "anthropic".
    pub provider: String,
    /// e.g. https://api.openai.com, http://127.0.0.1:11434 (Ollama), https://api.anthropic.com;
    /// `/v1/chat/completions` or `/v1/messages` is appended.
    pub base_url: String,
    pub model: String,
    /// Environment variable holding the API key (None: send no key, e.g. a local server).
    #[serde(default)]
    pub api_key_env: Option<String>,
    #[serde(default = "default_temperature")]
    pub temperature: f64,
    #[serde(default = "default_max_tokens")]
    pub max_tokens: u32,
    /// Whole request, connection to last byte, s.
    #[serde(default = "default_timeout")]
    pub timeout_s: f64,
    /// Further attempts after a 429, a 5xx or a transport failure.
    #[serde(default = "default_retries")]
    pub retries: u32,
    /// Set by `--llm record:` / `--llm replay:`, never by the TOML file: answers are recorded to
    /// or replayed from this cassette ([`crate::cassette`]).
    #[serde(default, skip_deserializing, skip_serializing_if = "Option::is_none")]
    pub cassette: Option<CassetteSpec>,
}

fn default_temperature() -> f64 {
    0.0
}
fn default_max_tokens() -> u32 {
    4096
}
fn default_timeout() -> f64 {
    120.0
}
fn default_retries() -> u32 {
    3
}

impl EndpointConfig {
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let c: Self = toml::from_str(&text).with_context(|| format!("LLM config {}", path.display()))?;
        c.check().with_context(|| format!("LLM config {}", path.display()))?;
        Ok(c)
    }

    pub fn check(&self) -> anyhow::Result<()> {
        if !["openai", "anthropic"].contains(&self.provider.as_str()) {
            bail!(
                "provider \"{}\" is unknown: use \"openai\" (any chat-completions server) or \"anthropic\"",
                self.provider
            );
        }
        if !(self.base_url.starts_with("http://") || self.base_url.starts_with("https://")) {
            bail!("base_url \"{}\" must start with http:// or https://", self.base_url);
        }
        if !(self.timeout_s.is_finite() && self.timeout_s > 0.0 && self.timeout_s <= 3600.0) {
            bail!("timeout_s = {} must be in (0, 3600]", self.timeout_s);
        }
        if self.retries > 10 {
            bail!("retries = {} is more than 10", self.retries);
        }
        if !(0.0..=2.0).contains(&self.temperature) {
            bail!("temperature = {} must be in [0, 2]", self.temperature);
        }
        Ok(())
    }
}

/// A piece of a message.
#[derive(Debug, Clone)]
pub enum Part {
    Text(String),
    /// PNG bytes.
    Png(Vec<u8>),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    User,
    Assistant,
}

#[derive(Debug, Clone)]
pub struct Message {
    pub role: Role,
    pub parts: Vec<Part>,
}

impl Message {
    pub fn text(role: Role, text: impl Into<String>) -> Self {
        Self { role, parts: vec![Part::Text(text.into())] }
    }
}

/// Token counts of one response, normalised: `input` counts every input token once (cached
/// ones included), `cached` is the part of it served from a prompt cache.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct Usage {
    pub input: u64,
    pub cached: u64,
    pub output: u64,
    /// Reasoning tokens, where the endpoint reports them (part of `output`).
    pub reasoning: Option<u64>,
    /// The endpoint's own usage object, unchanged.
    pub raw: Value,
}

#[derive(Debug, Clone)]
pub struct Completion {
    pub text: String,
    pub usage: Usage,
    /// HTTP attempts it took (1 without retries).
    pub attempts: u32,
    pub wall_s: f64,
    /// The response body as received.
    pub raw: Value,
    /// The endpoint stopped the answer at its token limit (`max_tokens`), not where the model
    /// ended it.
    pub truncated: bool,
}

/// Whether a response body says the answer was cut off at the token limit.
pub fn cut_off(provider: &str, raw: &Value) -> bool {
    if provider == "anthropic" {
        raw["stop_reason"] == "max_tokens"
    } else {
        raw["choices"][0]["finish_reason"] == "length"
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LlmError {
    #[error("missing API key: environment variable {0} is not set")]
    NoKey(String),
    #[error("{endpoint}: HTTP {status} after {attempts} attempt(s): {body}")]
    Status { endpoint: String, status: u16, attempts: u32, body: String },
    #[error("{endpoint}: {detail} after {attempts} attempt(s)")]
    Transport { endpoint: String, detail: String, attempts: u32 },
    #[error("{endpoint}: malformed response: {detail}")]
    Malformed { endpoint: String, detail: String },
    #[error(transparent)]
    Cassette(#[from] CassetteError),
}

/// The most a response body may hold.
const MAX_BODY: u64 = 16 << 20;
/// Longest wait honoured from a Retry-After header, s.
const MAX_RETRY_AFTER_S: f64 = 30.0;

pub struct Client {
    pub cfg: EndpointConfig,
    key: Option<String>,
    http: ureq::Agent,
    tape: Option<Tape>,
}

/// Where answers are recorded to or replayed from.
enum Tape {
    Record(Recorder),
    /// No HTTP at all: every answer comes from the cassette.
    Replay(Box<Player>),
}

impl Client {
    /// A client of the endpoint; with `cfg.cassette` set, one that records every answer to it
    /// (a new file) or answers from it alone.
    pub fn new(cfg: EndpointConfig) -> Result<Self, LlmError> {
        let tape = match &cfg.cassette {
            None => None,
            Some(CassetteSpec { mode: CassetteMode::Record, path }) => {
                Some(Tape::Record(Recorder::create(path, &cfg)?))
            }
            Some(CassetteSpec { mode: CassetteMode::Replay, path }) => {
                Some(Tape::Replay(Box::new(Player::open(path)?)))
            }
        };
        let key = match (&cfg.api_key_env, &tape) {
            (_, Some(Tape::Replay(_))) | (None, _) => None,
            (Some(var), _) => Some(std::env::var(var).map_err(|_| LlmError::NoKey(var.clone()))?),
        };
        let timeout = Duration::from_secs_f64(cfg.timeout_s);
        let http: ureq::Agent = ureq::Agent::config_builder()
            .timeout_global(Some(timeout))
            .http_status_as_error(false)
            .proxy(None)
            .max_redirects(0)
            .build()
            .into();
        Ok(Self { cfg, key, http, tape })
    }

    fn url(&self) -> String {
        let base = self.cfg.base_url.trim_end_matches('/');
        match self.cfg.provider.as_str() {
            "anthropic" => format!("{base}/v1/messages"),
            _ => format!("{base}/v1/chat/completions"),
        }
    }

    /// The request body in the endpoint's wire format.
    pub fn body(&self, system: &str, messages: &[Message]) -> Value {
        let b64 = |png: &[u8]| base64::engine::general_purpose::STANDARD.encode(png);
        if self.cfg.provider == "anthropic" {
            let mut msgs: Vec<Value> = messages
                .iter()
                .map(|m| {
                    let content: Vec<Value> = m
                        .parts
                        .iter()
                        .map(|p| match p {
                            Part::Text(t) => json!({"type": "text", "text": t}),
                            Part::Png(png) => json!({"type": "image", "source": {
                                "type": "base64", "media_type": "image/png", "data": b64(png)}}),
                        })
                        .collect();
                    json!({"role": m.role, "content": content})
                })
                .collect();
            // Anthropic caches a prompt prefix only up to a block marked `cache_control`: the
            // system prompt (the same for every request of an episode) and the conversation so
            // far (the next request starts with it). Two of the four marks a request may hold.
            let cached = json!({"type": "ephemeral"});
            if let Some(last) = msgs.last_mut().and_then(|m| m["content"].as_array_mut()).and_then(|c| c.last_mut()) {
                last["cache_control"] = cached.clone();
            }
            json!({"model": self.cfg.model, "max_tokens": self.cfg.max_tokens, "temperature": self.cfg.temperature,
                   "system": [{"type": "text", "text": system, "cache_control": cached}], "messages": msgs})
        } else {
            let mut msgs = vec![json!({"role": "system", "content": system})];
            msgs.extend(messages.iter().map(|m| {
                let content: Vec<Value> = m
                    .parts
                    .iter()
                    .map(|p| match p {
                        Part::Text(t) => json!({"type": "text", "text": t}),
                        Part::Png(png) => json!({"type": "image_url", "image_url": {
                            "url": format!("data:image/png;base64,{}", b64(png))}}),
                    })
                    .collect();
                json!({"role": m.role, "content": content})
            }));
            json!({"model": self.cfg.model, "max_tokens": self.cfg.max_tokens, "temperature": self.cfg.temperature,
                   "messages": msgs})
        }
    }

    /// One completion: from the endpoint (recorded when a cassette records), or from the
    /// cassette alone when it replays (`attempts` 0: no HTTP).
    pub fn complete(&self, system: &str, messages: &[Message]) -> Result<Completion, LlmError> {
        match &self.tape {
            None => self.over_http(system, messages),
            Some(Tape::Record(rec)) => {
                // Canonical first: a request that cannot be keyed costs no tokens.
                let c =
                    cassette::canonical(&self.cfg.model, self.cfg.temperature, self.cfg.max_tokens, system, messages)?;
                let out = self.over_http(system, messages)?;
                rec.append(&c, &out)?;
                Ok(out)
            }
            Some(Tape::Replay(player)) => {
                let t0 = Instant::now();
                let e = &player.endpoint;
                let c = cassette::canonical(&e.model, e.temperature, e.max_tokens, system, messages)?;
                let r = player.answer(&c)?;
                Ok(Completion {
                    text: r.text,
                    usage: r.usage,
                    attempts: 0,
                    wall_s: t0.elapsed().as_secs_f64(),
                    truncated: cut_off(&e.provider, &r.raw),
                    raw: r.raw,
                })
            }
        }
    }

    /// One completion over HTTP, retried on 429, 5xx and transport failures with exponential
    /// backoff (0.5 s doubling, or the server's Retry-After up to 30 s).
    fn over_http(&self, system: &str, messages: &[Message]) -> Result<Completion, LlmError> {
        let url = self.url();
        let body = serde_json::to_vec(&self.body(system, messages)).map_err(|e| LlmError::Malformed {
            endpoint: url.clone(),
            detail: format!("request not serialisable: {e}"),
        })?;
        let t0 = Instant::now();
        let mut attempt = 0;
        loop {
            attempt += 1;
            let mut req = self.http.post(&url).header("content-type", "application/json");
            match (&self.key, self.cfg.provider.as_str()) {
                (Some(k), "anthropic") => req = req.header("x-api-key", k),
                (Some(k), _) => req = req.header("authorization", format!("Bearer {k}")),
                (None, _) => {}
            }
            if self.cfg.provider == "anthropic" {
                req = req.header("anthropic-version", "2023-06-01");
            }
            let retry_after;
            let err = match req.send(&body[..]) {
                Ok(resp) => {
                    let status = resp.status().as_u16();
                    retry_after = resp
                        .headers()
                        .get("retry-after")
                        .and_then(|v| v.to_str().ok())
                        .and_then(|v| v.trim().parse::<f64>().ok())
                        .filter(|s| s.is_finite());
                    let text = resp.into_body().with_config().limit(MAX_BODY).read_to_string();
                    match (status, text) {
                        (200, Ok(text)) => return self.parse(&url, &text, attempt, t0),
                        (200, Err(e)) => LlmError::Transport {
                            endpoint: url.clone(),
                            detail: format!("reading the body: {e}"),
                            attempts: attempt,
                        },
                        (s, text) => {
                            let body: String = text.unwrap_or_default().chars().take(400).collect();
                            let e = LlmError::Status { endpoint: url.clone(), status: s, attempts: attempt, body };
                            if !(s == 429 || (500..600).contains(&s)) {
                                return Err(e);
                            }
                            e
                        }
                    }
                }
                Err(e) => {
                    retry_after = None;
                    LlmError::Transport { endpoint: url.clone(), detail: e.to_string(), attempts: attempt }
                }
            };
            if attempt > self.cfg.retries {
                return Err(err);
            }
            let backoff =
                retry_after.map_or(0.5 * f64::from(1u32 << (attempt - 1).min(6)), |s| s.clamp(0.0, MAX_RETRY_AFTER_S));
            std::thread::sleep(Duration::from_secs_f64(backoff));
        }
    }

    fn parse(&self, url: &str, text: &str, attempts: u32, t0: Instant) -> Result<Completion, LlmError> {
        let bad = |detail: String| LlmError::Malformed { endpoint: url.to_string(), detail };
        let v: Value = serde_json::from_str(text)
            .map_err(|e| bad(format!("not JSON ({e}): {}", text.chars().take(200).collect::<String>())))?;
        let (out, usage) = if self.cfg.provider == "anthropic" {
            let parts = v["content"].as_array().ok_or_else(|| bad("no content array".into()))?;
            let text: String = parts
                .iter()
                .filter(|p| p["type"] == "text")
                .filter_map(|p| p["text"].as_str())
                .collect::<Vec<_>>()
                .join("");
            (text, normalise_anthropic(&v["usage"]))
        } else {
            let text = v["choices"][0]["message"]["content"]
                .as_str()
                .ok_or_else(|| bad("no choices[0].message.content string".into()))?
                .to_string();
            (text, normalise_openai(&v["usage"]))
        };
        let truncated = cut_off(&self.cfg.provider, &v);
        Ok(Completion { text: out, usage, attempts, wall_s: t0.elapsed().as_secs_f64(), raw: v, truncated })
    }
}

fn n(v: &Value) -> u64 {
    v.as_u64().unwrap_or(0)
}

/// OpenAI: `prompt_tokens` already includes `prompt_tokens_details.cached_tokens`.
pub fn normalise_openai(u: &Value) -> Usage {
    Usage {
        input: n(&u["prompt_tokens"]),
        cached: n(&u["prompt_tokens_details"]["cached_tokens"]),
        output: n(&u["completion_tokens"]),
        reasoning: u["completion_tokens_details"]["reasoning_tokens"].as_u64(),
        raw: u.clone(),
    }
}

/// Anthropic: `input_tokens` excludes cache reads and cache writes, which are added once here.
pub fn normalise_anthropic(u: &Value) -> Usage {
    let read = n(&u["cache_read_input_tokens"]);
    Usage {
        input: n(&u["input_tokens"]) + read + n(&u["cache_creation_input_tokens"]),
        cached: read,
        output: n(&u["output_tokens"]),
        reasoning: None,
        raw: u.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn usage_counts_cached_input_once_in_both_formats() {
        let o = normalise_openai(&json!({"prompt_tokens": 1200, "completion_tokens": 80,
            "prompt_tokens_details": {"cached_tokens": 1000}, "completion_tokens_details": {"reasoning_tokens": 30}}));
        assert_eq!((o.input, o.cached, o.output, o.reasoning), (1200, 1000, 80, Some(30)));
        let a = normalise_anthropic(&json!({"input_tokens": 200, "output_tokens": 80,
            "cache_read_input_tokens": 1000, "cache_creation_input_tokens": 0}));
        assert_eq!((a.input, a.cached, a.output, a.reasoning), (1200, 1000, 80, None));
        let none = normalise_openai(&json!({"prompt_tokens": 10, "completion_tokens": 2}));
        assert_eq!((none.input, none.cached), (10, 0));
    }

    #[test]
    fn the_shipped_endpoint_files_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("endpoints");
        for f in ["openai.toml", "anthropic.toml", "ollama.toml"] {
            EndpointConfig::load(&dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e:#}"));
        }
    }

    #[test]
    fn configs_are_checked_with_the_reason() {
        let c = |s: &str| {
            toml::from_str::<EndpointConfig>(s)
                .map_err(|e| e.to_string())
                .and_then(|c| c.check().map(|_| c).map_err(|e| e.to_string()))
        };
        assert!(c("provider = \"openai\"\nbase_url = \"http://127.0.0.1:1\"\nmodel = \"m\"").is_ok());
        assert!(c("provider = \"gemini\"\nbase_url = \"http://x\"\nmodel = \"m\"").unwrap_err().contains("unknown"));
        assert!(c("provider = \"openai\"\nbase_url = \"ftp://x\"\nmodel = \"m\"").unwrap_err().contains("http://"));
        assert!(c("provider = \"openai\"\nbase_url = \"http://x\"\nmodel = \"m\"\nspeed = 1")
            .unwrap_err()
            .contains("unknown field"));
    }
}
