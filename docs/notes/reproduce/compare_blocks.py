"""Compare the generated blocks of two copies of docs/results.md, row by row.

    python docs/notes/reproduce/compare_blocks.py OLD.md NEW.md \
        reproduce,reproduce_stability,reproduce_pareto

Every "mean ± std (min–max)" cell of a table is matched by its row's text columns and its
column's name (a column only one side has is named, not compared); it is
within when |new mean - old mean| <= old std + new std (the two runs' seed spreads summed).
Every matched cell, plain numbers too, is also counted as identical (the same text) or not.
Timing columns are counted apart: they measure the machine as much as the model.
"""
import re
import sys

CELL = re.compile(r"^(-?[\d.e+-]+) ± ([\d.e+-]+|nan) \((.*)\)$")
# "given" is not a key: the blocks since 6592c95 split it into "trained with" and "given at
# inference", so rows are matched by the model's label (which names what it reads) instead
KEYS = ("scene", "fps", "model", "case", "source", "metric", "overrides")
TIMING = ("seconds_per_step", "s_per_step", "cell_minutes", "seconds_per_time_unit", "sim_s",
          "stage s", "on front")  # "on front": read off the timings


def block(text: str, name: str) -> str:
    return text[text.index(f"<!-- generated:{name}:begin"):text.index(f"<!-- generated:{name}:end")]


def tables(text: str) -> dict:
    found, title, lines = {}, None, text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("####"):
            title = line.strip("# ").strip()
        if line.startswith("|") and i + 1 < len(lines) and lines[i + 1].startswith("|---"):
            head = [x.strip() for x in line.strip("|").split("|")]
            rows = []
            for row in lines[i + 2:]:
                if not row.startswith("|"):
                    break
                rows.append([x.strip() for x in row.strip("|").split("|")])
            found[title] = (head, rows)
    return found


def cell(text: str) -> tuple[float, float] | None:
    m = CELL.match(text)
    if not m:
        return None
    try:
        return float(m.group(1)), 0.0 if m.group(2) == "nan" else float(m.group(2))
    except ValueError:
        return None


def main(old_path: str, new_path: str, names: str) -> None:
    old, new = open(old_path).read(), open(new_path).read()
    counts = {False: [0, 0], True: [0, 0]}  # timing? -> [compared, outside]
    same = {False: [0, 0], True: [0, 0]}    # timing? -> [matched cells, identical text]
    outside = []
    for name in names.split(","):
        before, after = tables(block(old, name)), tables(block(new, name))
        for title, (head, rows) in before.items():
            if title not in after:
                print(f"{name}: table {title!r} missing in the new block")
                continue
            new_head = after[title][0]
            added = [h for h in new_head if h not in head]
            gone = [h for h in head if h not in new_head]
            if added or gone:  # columns are matched by name: a new one is not compared
                print(f"{name}: table {title!r}: columns added {added}, gone {gone}")

            def key(row, head):
                return tuple(c for c, h in zip(row, head) if h in KEYS and cell(c) is None)

            matched: dict = {}  # rows with the same key are matched in their order
            for r in after[title][1]:
                matched.setdefault(key(r, new_head), []).append(dict(zip(new_head, r)))
            for row in rows:
                others = matched.get(key(row, head))
                other = others.pop(0) if others else None
                if other is None:
                    print(f"{name}: row {key(row, head)[:3]} missing in the new table")
                    continue
                for col, a in zip(head, row):
                    if col not in other:
                        continue
                    b = other[col]
                    if col not in KEYS:
                        same[col in TIMING][0] += 1
                        same[col in TIMING][1] += a == b
                    pa, pb = cell(a), cell(b)
                    if pa and pb:
                        timing = col in TIMING
                        counts[timing][0] += 1
                        if abs(pa[0] - pb[0]) > pa[1] + pb[1] + 1e-12 * max(abs(pa[0]), 1):
                            counts[timing][1] += 1
                            where = f"{title[:40]} | {key(row, head)[:3]} | {col}"
                            outside.append(f"{where} | {a} -> {b}")
    for timing, label in ((False, "error, energy and mass cells"), (True, "timing cells")):
        n, out = counts[timing]
        print(f"{label}: {n - out} of {n} within the summed seed spread, {out} outside; "
              f"of all {same[timing][0]} such cells, {same[timing][1]} identical")
    print("\n".join(outside))


if __name__ == "__main__":
    main(*sys.argv[1:4])
