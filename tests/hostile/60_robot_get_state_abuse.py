"""Robot: get_state with absurd image sizes, path-like camera names and wrong types; contained = every call raises ValueError/TypeError."""
from robo import get_state

CASES = [
    ("size 1e9 x 1e9", {"agentview": (10**9, 10**9)}),
    ("size 4097 x 4097", {"agentview": (4097, 4097)}),
    ("size 0 x 0", {"agentview": (0, 0)}),
    ("negative width", {"agentview": (-640, 480)}),
    ("string sizes", {"agentview": ("640", "480")}),
    ("path camera name", "../../etc/passwd"),
    ("NUL in camera name", "agentview\0wrist"),
    ("camera list of dicts", [{"agentview": (64, 64)}]),
    ("integer cameras", 12),
]
for label, cameras in CASES:
    try:
        st = get_state(cameras)
    except (ValueError, TypeError) as e:
        print(f"BLOCKED: {label}: {type(e).__name__}: {str(e)[:160]}")
        continue
    print(f"ESCAPED: get_state accepted {label}: images {sorted(st.get('image', {}))}")
