//! A static HTML viewer for a run folder: `index.html` next to the records, with the rounds
//! (decision, code, feedback, images), the metrics and the native verdict. The data is embedded
//! as JSON and drawn by a small script, so the file opens from disk with no server.

use std::path::Path;

use serde_json::{json, Value};

fn read_json(p: &Path) -> Value {
    std::fs::read_to_string(p).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or(Value::Null)
}

/// Writes `index.html` for the run in `dir` (and returns its path).
pub fn write(dir: &Path) -> anyhow::Result<std::path::PathBuf> {
    write_with(dir, read_json(&dir.join("result.json")))
}

/// [`write`] with the run's result given (an episode writes `result.json` after the page, last,
/// so a run folder that has it is whole).
pub fn write_with(dir: &Path, result: Value) -> anyhow::Result<std::path::PathBuf> {
    let rounds: Vec<Value> = std::fs::read_to_string(dir.join("transcript.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .map(|mut r: Value| {
            // Image files of the round, as relative links.
            let n = r["round"].as_u64().unwrap_or(0);
            let mut imgs: Vec<String> = std::fs::read_dir(dir.join(format!("rounds/{n:03}")))
                .map(|d| {
                    d.flatten()
                        .filter(|e| e.path().extension().is_some_and(|x| x == "png"))
                        .map(|e| format!("rounds/{n:03}/{}", e.file_name().to_string_lossy()))
                        .collect()
                })
                .unwrap_or_default();
            imgs.sort();
            // Then the images the program showed the model (`shown`, in the order attached).
            imgs.extend(
                r["shown"].as_array().into_iter().flatten().filter_map(|s| s["file"].as_str().map(str::to_string)),
            );
            r["images"] = json!(imgs);
            r
        })
        .collect();
    let data = json!({"config": read_json(&dir.join("config.json")), "result": result,
                      "rounds": rounds, "skills": read_json(&dir.join("skills.json"))});
    // No `<`, `>` or `&` in the data block: model or program text cannot end it or change how
    // the HTML parser reads it (JSON allows the \u escapes).
    let blob = serde_json::to_string(&data)?.replace('<', "\\u003c").replace('>', "\\u003e").replace('&', "\\u0026");
    let html = format!("{HEAD}<script id=\"data\" type=\"application/json\">{blob}</script>{SCRIPT}</body></html>\n");
    let path = dir.join("index.html");
    std::fs::write(&path, html)?;
    Ok(path)
}

const HEAD: &str = r#"<!doctype html><html><head><meta charset="utf-8"><title>r2g run</title>
<style>
body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1200px}
pre{background:#f4f4f4;padding:.6em;overflow-x:auto;white-space:pre-wrap;font-size:12px}
.round{border:1px solid #ccc;border-radius:6px;padding:.8em;margin:1em 0}
.viol{color:#b00;font-weight:bold}.ok{color:#070}.bad{color:#b00}
img{max-width:320px;margin-right:.5em;border:1px solid #ddd}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.2em .6em;text-align:right}
</style></head><body><h1 id="title">r2g run</h1><div id="summary"></div><div id="rounds"></div>
"#;

const SCRIPT: &str = r#"<script>
const d = JSON.parse(document.getElementById('data').textContent);
const el = (tag, attrs, ...kids) => { const e = document.createElement(tag);
  Object.assign(e, attrs || {}); kids.forEach(k => e.append(k)); return e; };
const r = d.result || {}, c = d.config || {};
document.getElementById('title').textContent = `${c.gym || 'run'}: ${c.task || ''}`;
const verdict = r.success === undefined ? 'not judged (run unfinished)' : (r.success ? 'success' : 'failure');
const s = document.getElementById('summary');
s.append(el('p', {className: r.success ? 'ok' : 'bad', id: 'verdict'}, 'Native verdict: ' + verdict));
const t = el('table', {id: 'metrics'});
[['responses', r.responses], ['tokens in / cached / out', `${r.tokens_in} / ${r.tokens_cached} / ${r.tokens_out}`],
 ['wall s', (r.wall_s || 0).toFixed(1)], ['model s', (r.model_s || 0).toFixed(1)],
 ['execution s', (r.exec_s || 0).toFixed(1)], ['host overhead s', (r.overhead_s || 0).toFixed(2)],
 ['stop', r.stop_reason]].forEach(([k, v]) => t.append(el('tr', {}, el('th', {}, k), el('td', {}, String(v)))));
s.append(t);
const sk = d.skills;
if (sk && sk.ranked) {
  // Which skills the episode was given, and why the others were not.
  const st = el('table', {id: 'skills'}, el('tr', {}, el('th', {}, 'skill'), el('th', {}, 'relevance'),
    el('th', {}, 'success lower bound'), el('th', {}, 'score'), el('th', {}, 'given')));
  for (const k of sk.ranked) st.append(el('tr', {}, el('td', {}, `${k.id} v${k.version}`), el('td', {}, k.relevance.toFixed(3)),
    el('td', {}, k.success_lower_bound.toFixed(3)), el('td', {}, k.score.toFixed(3)), el('td', {}, (sk.chosen || []).includes(k.id) ? 'yes' : 'no')));
  s.append(el('h2', {}, `Skills selected: ${(sk.chosen || []).join(', ') || 'none'}`), st);
  for (const [id, why] of sk.excluded || []) s.append(el('p', {}, `${id}: left out, ${why}`));
}
const box = document.getElementById('rounds');
for (const rd of d.rounds) {
  const div = el('div', {className: 'round'});
  const dec = rd.decision || {};
  div.append(el('h3', {}, `Round ${rd.round}` + (rd.observe_only ? ' (observation only)' : '')));
  if (rd.error) div.append(el('p', {className: 'viol'}, rd.error));
  if (dec.observation) div.append(el('p', {}, el('b', {}, 'Observation: '), dec.observation));
  if (dec.plan) div.append(el('p', {}, el('b', {}, 'Plan: '), dec.plan));
  if (dec.code) div.append(el('pre', {className: 'code'}, dec.code));
  if (dec.expected) div.append(el('p', {}, el('b', {}, 'Expected: '), dec.expected));
  if (dec.stop) div.append(el('p', {}, el('b', {}, 'Stop: '), dec.stop));
  if (rd.exec && rd.exec.violation) div.append(el('p', {className: 'viol'}, 'Sandbox: ' + rd.exec.violation));
  if (rd.feedback) div.append(el('pre', {className: 'feedback'}, rd.feedback));
  for (const src of rd.images || []) div.append(el('img', {src, alt: src}));
  const u = rd.usage || {};
  div.append(el('p', {}, `tokens in ${u.input} (cached ${u.cached}), out ${u.output}; model ${(rd.model_s || 0).toFixed(2)} s`
    + (rd.exec ? `; execution ${(rd.exec.wall_s || 0).toFixed(2)} s, ${rd.exec.control_steps} control steps` : '')));
  box.append(div);
}
</script>
"#;
