"""Compare two runs' metrics.json, every numeric entry: how many, which differ (wall time
apart: it measures the machine), which only one run has.

    python docs/notes/behaviour/diff_metrics.py NAME BEFORE.json AFTER.json
"""
import json
import sys


def flat(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flat(value, f"{prefix}{key}."))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out[prefix + key] = value
    return out


name, before, after = sys.argv[1], *(flat(json.load(open(p))) for p in sys.argv[2:4])
common = sorted(set(before) & set(after))
differ = [k for k in common if before[k] != after[k] and not k.endswith("wall_time_s")]
print(f"{name}: {len(common)} metrics in both, {len(differ)} differ (wall time apart), "
      f"{len(set(before) - set(after))} only before, {len(set(after) - set(before))} only after")
for key in differ:
    print(f"  {key}: {before[key]} -> {after[key]}")
sys.exit(1 if differ else 0)
