//! The LLM clients against the repo's scripted server over real HTTP on loopback, in both wire
//! formats: usage with and without cache counts, 429 then success, 500 then success, a timeout,
//! malformed JSON, a non-JSON body and an endless stream.

use std::io::BufRead;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Instant;

use agent_host::llm::{Client, EndpointConfig, LlmError, Message, Part, Role};

struct Server {
    child: Child,
    port: u16,
}

impl Server {
    fn start() -> Self {
        let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
        let mut child = Command::new(root.join(".venv/bin/python"))
            .arg(root.join("agent-host/py/scripted_llm.py"))
            .arg("--script")
            .arg(root.join("agent-host/scripted/pick_block_plate.json"))
            .args(["--port", "0"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("python and the scripted server (run `make robo`)");
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut line).expect("line");
        let port = line.trim().strip_prefix("LISTENING ").and_then(|p| p.parse().ok()).expect("LISTENING <port>");
        Self { child, port }
    }

    fn client(&self, provider: &str, fault: &str, timeout_s: f64, retries: u32) -> Client {
        std::env::set_var("R2G_TEST_KEY", "test-key");
        let base = if fault.is_empty() {
            format!("http://127.0.0.1:{}", self.port)
        } else {
            format!("http://127.0.0.1:{}/fault/{fault}", self.port)
        };
        let cfg = EndpointConfig {
            provider: provider.into(),
            base_url: base,
            model: "scripted".into(),
            api_key_env: Some("R2G_TEST_KEY".into()),
            temperature: 0.0,
            max_tokens: 1024,
            timeout_s,
            retries,
            cassette: None,
        };
        Client::new(cfg).expect("client")
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // SAFETY: our own child, by pid.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let _ = self.child.wait();
    }
}

/// A tiny valid PNG (2x2, RGB).
fn png() -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut e = png::Encoder::new(&mut out, 2, 2);
        e.set_color(png::ColorType::Rgb);
        let mut w = e.write_header().expect("header");
        w.write_image_data(&[255, 0, 0].repeat(4)).expect("pixels");
    }
    out
}

fn conversation(turns: usize) -> Vec<Message> {
    let mut m = vec![Message { role: Role::User, parts: vec![Part::Text("observe".into()), Part::Png(png())] }];
    for i in 0..turns {
        m.push(Message::text(Role::Assistant, format!("<stop>turn {i}</stop>")));
        m.push(Message { role: Role::User, parts: vec![Part::Text(format!("feedback {i}")), Part::Png(png())] });
    }
    m
}

#[test]
fn both_formats_return_the_scripted_turn_with_normalised_usage_and_cache_counts() {
    let s = Server::start();
    for provider in ["openai", "anthropic"] {
        let c = s.client(provider, "", 30.0, 0);
        let first = c.complete("system prompt", &conversation(0)).expect("first");
        assert!(first.text.contains("<observation>"), "{provider}: {}", first.text);
        assert_eq!(first.attempts, 1);
        // The next turn repeats the first messages: they are served from the cache.
        let second = c.complete("system prompt", &conversation(1)).expect("second");
        let u = &second.usage;
        assert!(u.cached > 0 && u.cached < u.input, "{provider}: {u:?}");
        assert!(u.output > 0);
        if provider == "anthropic" {
            // input_tokens excludes cache reads; ours counts them once.
            let raw_in = u.raw["input_tokens"].as_u64().expect("input_tokens");
            assert_eq!(u.input, raw_in + u.raw["cache_read_input_tokens"].as_u64().expect("cache read"));
        } else {
            assert_eq!(u.input, u.raw["prompt_tokens"].as_u64().expect("prompt_tokens"));
        }
        // A server that reports no cache fields: zero cached, input still counted.
        let nc = s.client(provider, "nocache", 30.0, 0).complete("system prompt", &conversation(1)).expect("nocache");
        assert_eq!(nc.usage.cached, 0, "{provider}");
        assert_eq!(nc.usage.input, u.input, "{provider}");
    }
}

#[test]
fn rate_limits_and_server_errors_are_retried_then_succeed() {
    let s = Server::start();
    for (provider, fault) in [("openai", "429once"), ("anthropic", "500once")] {
        let t0 = Instant::now();
        let c = s.client(provider, fault, 30.0, 2).complete("sys", &conversation(0)).expect("succeeds after a retry");
        assert_eq!(c.attempts, 2, "{provider} {fault}");
        assert!(t0.elapsed().as_secs_f64() < 10.0);
    }
    // Without retries, the 429 is the answer, with its status.
    let s2 = Server::start();
    match s2.client("openai", "429once", 30.0, 0).complete("sys", &conversation(0)) {
        Err(LlmError::Status { status: 429, attempts: 1, .. }) => {}
        other => panic!("expected a 429, got {:?}", other.map(|c| c.text)),
    }
}

#[test]
fn a_slow_server_times_out_within_the_bound_for_every_attempt() {
    let s = Server::start();
    let t0 = Instant::now();
    let r = s.client("anthropic", "slow", 1.0, 1).complete("sys", &conversation(0));
    let took = t0.elapsed().as_secs_f64();
    match r {
        Err(LlmError::Transport { attempts: 2, detail, .. }) => assert!(detail.contains("timeout"), "{detail}"),
        other => panic!("expected a timeout, got {:?}", other.map(|c| c.text)),
    }
    assert!((1.5..6.0).contains(&took), "two 1 s attempts and a 0.5 s backoff took {took:.1} s");
}

#[test]
fn malformed_non_json_and_endless_bodies_fail_with_a_precise_error() {
    let s = Server::start();
    for provider in ["openai", "anthropic"] {
        match s.client(provider, "malformed", 10.0, 0).complete("sys", &conversation(0)) {
            Err(LlmError::Malformed { detail, .. }) => assert!(detail.contains("not JSON"), "{detail}"),
            other => panic!("{provider}: expected malformed, got {:?}", other.map(|c| c.text)),
        }
        match s.client(provider, "nojson", 10.0, 0).complete("sys", &conversation(0)) {
            Err(LlmError::Malformed { detail, .. }) => assert!(detail.contains("not JSON"), "{detail}"),
            other => panic!("{provider}: expected malformed, got {:?}", other.map(|c| c.text)),
        }
    }
    let t0 = Instant::now();
    match s.client("openai", "endless", 20.0, 0).complete("sys", &conversation(0)) {
        Err(LlmError::Transport { detail, .. }) => {
            assert!(detail.contains("body") || detail.contains("limit"), "{detail}")
        }
        other => panic!("expected the body limit, got {:?}", other.map(|c| c.text)),
    }
    assert!(t0.elapsed().as_secs_f64() < 20.0, "stopped by the 16 MiB body limit, not the timeout");
}

/// Records a conversation from the scripted server over HTTP, stops the server, and replays it
/// from the cassette alone: the same answers and token counts, for both wire formats; a
/// re-encoded image hits the same answer; a changed request fails with its key.
#[test]
fn a_recorded_conversation_replays_without_the_server() {
    use agent_host::cassette::{CassetteMode, CassetteSpec};
    let dir = std::env::temp_dir().join(format!("r2g-llm-cassette-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    for provider in ["openai", "anthropic"] {
        let path = dir.join(format!("{provider}.jsonl"));
        let live: Vec<_> = {
            let s = Server::start();
            let mut cfg = s.client(provider, "", 30.0, 0).cfg;
            cfg.cassette = Some(CassetteSpec { mode: CassetteMode::Record, path: path.clone() });
            let c = Client::new(cfg).expect("recording client");
            (0..3).map(|turns| c.complete("system prompt", &conversation(turns)).expect("live")).collect()
        }; // the server is gone from here on
        let replay = EndpointConfig {
            provider: "openai".into(),
            base_url: "http://127.0.0.1:1".into(), // nothing listens: it must not be used
            model: "replayed".into(),
            api_key_env: Some("R2G_UNSET_KEY_FOR_REPLAY".into()), // nor need a key
            temperature: 1.0,
            max_tokens: 1,
            timeout_s: 1.0,
            retries: 0,
            cassette: Some(CassetteSpec { mode: CassetteMode::Replay, path: path.clone() }),
        };
        let c = Client::new(replay.clone()).expect("replaying client");
        for (turns, l) in live.iter().enumerate() {
            let r = c.complete("system prompt", &conversation(turns)).expect("replayed");
            assert_eq!((&r.text, &r.usage, r.attempts), (&l.text, &l.usage, 0), "{provider} turn {turns}");
        }
        assert!(live[1].usage.cached > 0, "{provider}: the recorded cache counts are replayed");
        // The same pixels in another PNG encoding (RGBA, best compression).
        let mut msgs = conversation(1);
        let mut rgba = Vec::new();
        {
            let mut e = png::Encoder::new(&mut rgba, 2, 2);
            e.set_color(png::ColorType::Rgba);
            e.set_compression(png::Compression::High);
            let mut w = e.write_header().expect("header");
            w.write_image_data(&[255, 0, 0, 255].repeat(4)).expect("pixels");
        }
        assert_ne!(rgba, png());
        msgs[2].parts[1] = Part::Png(rgba);
        // Each recorded answer is served once: the same request again is a miss, loudly.
        match c.complete("system prompt", &msgs) {
            Err(LlmError::Cassette(e)) => assert!(e.to_string().contains("recorded 1 time(s)"), "{e}"),
            other => panic!("{provider}: a second ask must miss, got {:?}", other.map(|c| c.text)),
        }
        // From a fresh replay of the cassette, the same pixels are the same request.
        let c = Client::new(replay).expect("replaying client");
        assert_eq!(c.complete("system prompt", &msgs).expect("same pixels").text, live[1].text);
        // Another system prompt is another request.
        match c.complete("system prompt!", &conversation(1)) {
            Err(LlmError::Cassette(e)) => {
                let e = e.to_string();
                assert!(e.contains("is not in the cassette") && e.contains("system differs from character 13"), "{e}")
            }
            other => panic!("{provider}: expected a miss, got {:?}", other.map(|c| c.text)),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_answer_cut_off_at_the_token_limit_is_marked_and_refused() {
    let s = Server::start();
    for provider in ["openai", "anthropic"] {
        let whole = s.client(provider, "", 30.0, 0).complete("sys", &conversation(0)).expect("whole");
        assert!(!whole.truncated, "{provider}");
        let cut = s.client(provider, "cutoff", 30.0, 0).complete("sys", &conversation(0)).expect("cut");
        assert!(cut.truncated && cut.text.len() < whole.text.len(), "{provider}");
        let d = agent_host::episode::Decision::parse(&cut.text);
        let why = d.problem(cut.truncated).expect("a cut-off reply is not used");
        assert!(why.contains("token limit"), "{why}");
        // The same text ending by itself runs: an unclosed tag alone is no reason to refuse.
        assert!(d.problem(false).is_none());
    }
}

#[test]
fn anthropic_requests_mark_the_system_prompt_and_the_conversation_for_its_cache() {
    let s = Server::start();
    let body = s.client("anthropic", "", 30.0, 0).body("sys", &conversation(1));
    assert_eq!(body["system"][0]["cache_control"]["type"], "ephemeral");
    let last = body["messages"].as_array().and_then(|m| m.last()).expect("messages");
    assert_eq!(
        last["content"].as_array().and_then(|c| c.last()).expect("blocks")["cache_control"]["type"],
        "ephemeral"
    );
    assert_eq!(body.to_string().matches("cache_control").count(), 2, "two of the four marks a request may hold");
    // OpenAI-compatible servers cache a repeated prefix by themselves: no marks.
    assert!(!s.client("openai", "", 30.0, 0).body("sys", &conversation(1)).to_string().contains("cache_control"));
}
