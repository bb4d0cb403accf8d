#!/usr/bin/env python3
"""Tokens a real model's episode costs: the two real-model runs (tests/data/real-model) served turn
by turn through `r2g episode --llm scripted:<cassette>`, per request and per episode, in one or
both wire formats. Prints a table, then one JSON object.

    .venv/bin/python bench/py/prompt_tokens.py [--r2g target/release/r2g] [--provider openai|anthropic|both]

Every figure is an estimate, labelled so: `usage` is the scripted server's simulated count
(characters / 4 + 800 per image; cached = what the wire format's prompt cache would serve: for
OpenAI-compatible servers the repeated prefix, for Anthropic only up to `cache_control` marks);
`estimate` is the host's own (characters / 4 + 765 per image; cached = the prefix a request shares
with the one before). `--r2g` runs another build (for example an older checkout's binary) on the
same replays, the baseline of a before/after comparison.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUNS = {"stack_bowls": ("101", "xy=0.04,yaw=20"), "open_drawer": ("201", "xy=0.03,yaw=10")}


def replay(r2g: Path, gym: str, provider: str, out: Path) -> dict:
    seed, perturb = RUNS[gym]
    cassette = ROOT / "tests" / "data" / "real-model" / gym / "episode.cassette.jsonl"
    p = subprocess.run([str(r2g), "episode", gym, "--llm", f"scripted:{cassette}", "--provider", provider,
                        "--seed", seed, "--perturb", perturb, "--out", str(out), "--memory", str(out.parent / "mem")],
                       capture_output=True, text=True, timeout=1800)
    if not p.stdout.strip():
        sys.exit(f"{gym} ({provider}): r2g episode printed nothing: {p.stderr[-2000:]}")
    result = json.loads(p.stdout.strip().splitlines()[-1])
    rounds = [json.loads(line) for line in (out / "transcript.jsonl").read_text().splitlines()]
    per = [{"round": r["round"], "input": r["usage"]["input"], "cached": r["usage"]["cached"],
            "estimate": r.get("estimate")} for r in rounds if "usage" in r]
    return {"gym": gym, "provider": provider, "success": result["success"], "violations": result["violations"],
            "responses": result["responses"], "tokens_in": result["tokens_in"], "tokens_cached": result["tokens_cached"],
            "tokens_in_estimated": result.get("tokens_in_estimated"),
            "tokens_cached_estimated": result.get("tokens_cached_estimated"),
            "system_prompt_chars": len((out / "system_prompt.md").read_text()), "per_request": per}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--r2g", type=Path, default=ROOT / "target" / "release" / "r2g")
    ap.add_argument("--provider", default="both", choices=["openai", "anthropic", "both"])
    a = ap.parse_args()
    providers = ["openai", "anthropic"] if a.provider == "both" else [a.provider]
    rows = []
    with tempfile.TemporaryDirectory(prefix="r2g-prompt-tokens-") as tmp:
        for gym in RUNS:
            for provider in providers:
                rows.append(replay(a.r2g, gym, provider, Path(tmp) / f"{gym}-{provider}" / "run"))
    print(f"{'gym':<12} {'wire':<9} {'ok':<3} {'req':>3} {'in/request':>11} {'in/episode':>10} {'cached':>8} "
          f"{'uncached':>8} {'est. in':>8} {'est. cached':>11} {'system chars':>12}")
    for r in rows:
        n = max(r["responses"], 1)
        print(f"{r['gym']:<12} {r['provider']:<9} {'yes' if r['success'] else 'no':<3} {r['responses']:>3} "
              f"{r['tokens_in'] / n:>11.0f} {r['tokens_in']:>10} {r['tokens_cached']:>8} "
              f"{r['tokens_in'] - r['tokens_cached']:>8} {r['tokens_in_estimated'] or 0:>8} "
              f"{r['tokens_cached_estimated'] or 0:>11} {r['system_prompt_chars']:>12}")
    print("(estimates: scripted-server usage = chars/4 + 800/image; host estimate = chars/4 + 765/image)")
    print(json.dumps({"r2g": str(a.r2g), "label": "estimates, not a provider's counts", "episodes": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
