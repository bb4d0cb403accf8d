"""Prints the summary of an `r2g episode` JSON line (stdin); exits 1 unless it succeeded."""
import json
import sys

v = json.loads(sys.stdin.read().strip().splitlines()[-1])
print(
    f"  success {v['success']}: {v['responses']} responses, {v['executions']} programs, {v['violations']} violations;"
    f" tokens in {v['tokens_in']} (cached {v['tokens_cached']}), out {v['tokens_out']};"
    f" wall {v['wall_s']:.1f} s = model {v['model_s']:.1f} + programs {v['exec_s']:.1f} + host {v['overhead_s']:.2f}"
)
print(f"  records and viewer: {v['run_dir']}/index.html")
sys.exit(0 if v["success"] else 1)
