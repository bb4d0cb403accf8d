#!/usr/bin/env bash
# make demo: bring up pick_block_plate, drive it from Python through robo, shut it down.
set -uo pipefail
cd "$(dirname "$0")/.."
instance="demo$$"
out=demo-out
mkdir -p "$out"
log=$(mktemp)
rm -rf "$out/episodes"
target/release/r2g up pick_block_plate --instance "$instance" --trace-dir "$out/episodes" >"$log" &
up=$!
cleanup() { kill -TERM "$up" 2>/dev/null; wait "$up" 2>/dev/null; rm -f "$log"; }
trap cleanup EXIT
for _ in $(seq 1 600); do
  grep -q "^READY" "$log" && break
  kill -0 "$up" 2>/dev/null || { echo "demo: r2g up failed" >&2; exit 1; }
  sleep 0.1
done
grep -q "^READY" "$log" || { echo "demo: r2g up was not ready within 60 s" >&2; exit 1; }
echo "demo: $(cat "$log")"
R2G_INSTANCE="$instance" .venv/bin/python demo/demo.py "$out"
rc=$?
echo "demo: images in $out/ (agentview.png, wrist.png)"
echo "demo: every gym's demonstration replayed in lockstep and judged natively:"
for gym in $(target/release/r2g gyms); do
  line=$(target/release/r2g replay "$gym" --out "$out/replay" 2>/dev/null | tail -1)
  ok=$(echo "$line" | .venv/bin/python -c 'import json,sys; v=json.load(sys.stdin); print("success" if v["success"] else "FAILED", v["trace_sha256"][:16])' 2>/dev/null || echo "ERROR")
  printf '  %-18s %s\n' "$gym" "$ok"
  case "$ok" in success*) ;; *) rc=1 ;; esac
done
# The agent loop: an LLM writes stage programs that run in the sandbox against a live gym.
# R2G_LLM may name an endpoint TOML file; without one, the recorded conversation replays offline.
llm="${R2G_LLM:-scripted}"
echo "demo: the stage-code agent loop on pick_block_plate (LLM: $llm), sandboxed, judged natively:"
rm -rf "$out/agent-run"
line=$(target/release/r2g episode pick_block_plate --llm "$llm" --out "$out/agent-run" --memory "$out/agent-memory" 2>"$out/agent-run.log" | tail -1)
echo "$line" | .venv/bin/python demo/episode_summary.py || { echo "  the agent episode failed; see $out/agent-run.log"; rc=1; }
echo "demo: exit $rc"
exit $rc
