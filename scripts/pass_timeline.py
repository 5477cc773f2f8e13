#!/usr/bin/env python3
"""Reads `scripts/pass-timeline`'s log and perf sched trace: see there.

usage: pass_timeline.py LOG SCHED OFFSET [FROM_MS:TO_MS:STEP_MS]
OFFSET is realtime - monotonic (the log's timestamps are realtime, perf's monotonic); the
optional range prints the CPU split in steps, with the tile starts (s), ends (e) and pass ends.
"""
import collections
import datetime
import re
import subprocess
import sys

log, sched, offset = sys.argv[1], sys.argv[2], float(sys.argv[3])


def when(line):
    stamp = re.match(r'(\S+?)Z', line).group(1)
    t = datetime.datetime.fromisoformat(stamp).replace(tzinfo=datetime.timezone.utc)
    return t.timestamp() - offset


tiles, grants, passes, done = [], [], [], None
for line in open(log):
    if m := re.search(r'rendered in ([\d.]+)s, (accepted|dropped)', line):
        t = when(line)
        tiles.append((t - float(m.group(1)), t))
    elif 'leased tile' in line:
        grants.append(when(line))
    elif m := re.search(r'pass (\d+) done at [\d.]+s: (.*)', line):
        passes.append((when(line), m.group(2)))
    elif 'done in' in line:
        done = when(line)
# A tile or lease belongs to the pass whose end comes after it (log lines of a pass's last tile
# may follow its pass end's).
ends = [e for e, _ in passes]
def pass_of(t):
    return sum(1 for e in ends if e < t)
by_pass = collections.defaultdict(list)
for s, e in tiles:
    by_pass[pass_of(s)].append((s, e))
first_lease = collections.defaultdict(list)
for g in grants:
    first_lease[pass_of(g)].append(g)

# CPU time by class from the trace: each sched-out line closes a run of its task.
trace = subprocess.run(['perf', 'sched', 'timehist', '-i', sched],
                       capture_output=True, text=True).stdout
runs, ours = [], set()
for line in trace.splitlines():
    f = line.split()
    if len(f) < 6:
        continue
    try:
        t, ran = float(f[0]), float(f[-1]) / 1e3
    except ValueError:
        continue
    name = ' '.join(f[2:-3])
    m = re.search(r'\[(\d+)(?:/(\d+))?\]$', name)
    pid = (m.group(2) or m.group(1)) if m else None
    if 'render' in name:
        ours.add(pid)
    runs.append((t - ran, t, name, pid))
spans = collections.defaultdict(list)
for a, b, name, pid in runs:
    kind = ('render' if 'render' in name else 'idle' if name.startswith('<idle>')
            else 'farm' if pid in ours else 'other')
    spans[kind].append((a, b))


def cpu(a, b):
    got = collections.Counter()
    for kind, ss in spans.items():
        for x, y in ss:
            o = min(y, b) - max(x, a)
            if o > 0:
                got[kind] += o * 1e3
    return got


count = max(by_pass) + 1 if by_pass else 0
start = [min(first_lease[k]) if first_lease[k] else min(s for s, _ in by_pass[k])
         for k in range(count)]
t0 = start[0]
ms = lambda t: (t - t0) * 1e3
print(f"{'pass':>4} {'first':>7} {'last tile':>9} {'pass end':>8} {'next':>7} | "
      f"{'window':>6} {'render':>6} {'farm':>5} {'other':>5} {'idle':>5} (CPU-ms) | tiles")
for k in range(count):
    last = max(e for _, e in by_pass[k])
    end = ends[k] if k < len(ends) else last
    nxt = start[k + 1] if k + 1 < count else (done or end)
    c = cpu(start[k], nxt)
    note = passes[k][1] if k < len(passes) else ''
    print(f"{k:>4} {ms(start[k]):7.1f} {ms(last):9.1f} {ms(end):8.1f} {ms(nxt):7.1f} | "
          f"{ms(nxt) - ms(start[k]):6.1f} {c['render']:6.1f} {c['farm']:5.1f} {c['other']:5.1f} "
          f"{c['idle']:5.1f} | {len(by_pass[k])} {note}")
end = done or ends[-1]
c = cpu(t0, end)
print(f"first lease to done: {ms(end):.1f} ms; CPU-ms render {c['render']:.1f}, farm {c['farm']:.1f}, "
      f"other {c['other']:.1f}, idle {c['idle']:.1f}; render threads {c['render'] / ms(end):.2f} cores")
if len(sys.argv) > 4:
    a, b, step = (float(x) / 1e3 for x in sys.argv[4].split(':'))
    t = t0 + a
    while t < t0 + b:
        c = cpu(t, t + step)
        ev = [f"s{pass_of(s)}" for s, _ in tiles if t <= s < t + step]
        ev += [f"e{pass_of(s)}" for s, e in tiles if t <= e < t + step]
        ev += [f"PASS{i}" for i, e in enumerate(ends) if t <= e < t + step]
        print(f"{ms(t):7.1f} render {c['render']:5.1f} farm {c['farm']:5.1f} "
              f"other {c['other']:5.1f} idle {c['idle']:5.1f}  {' '.join(ev)}")
        t += step
