import sys, collections
idle_syms = ('find_work','wait_until_cold','Stealer','with_handle','crossbeam','sched_yield','__schedule','finish_task_switch','do_syscall','futex','syscall','yield','try_advance','entry_SYSCALL','_raw_spin','pick_next','do_sched_yield')
def cls(sym):
    if any(k in sym for k in idle_syms): return 'idle'
    if 'ingest' in sym or 'pair_in_place' in sym or 'worth_pairing' in sym or 'FastTris' in sym: return 'ingest'
    if 'gather' in sym or 'ids_in_leaf' in sym or 'prim_prefix' in sym: return 'leaf'
    if 'emit' in sym or 'copy_block' in sym or 'encode' in sym or 'wide_' in sym: return 'emit'
    if 'arbor::accel' in sym: return 'sah'
    return 'other'
samples = []
for line in sys.stdin:
    parts = line.split()
    if len(parts) < 3: continue
    try:
        t = float(parts[1].rstrip(':'))
    except ValueError:
        continue
    sym = ' '.join(parts[2:])
    samples.append((t, cls(sym)))
samples.sort()
# build starts: ingest samples after >= 3 ms without ingest
starts = []
last_ing = -1e9
for t, c in samples:
    if c == 'ingest':
        if t - last_ing > 0.003: starts.append(t)
        last_ing = t
B = 0.0005
hist = collections.defaultdict(lambda: collections.Counter())
nb = 0
for i, s0 in enumerate(starts[2:-1]):
    nb += 1
for t, c in samples:
    # find the build containing t
    import bisect
    k = bisect.bisect_right(starts, t) - 1
    if k < 2 or k >= len(starts) - 1: continue
    rel = t - starts[k]
    if rel > 0.030: continue
    hist[int(rel / B)][c] += 1
print('builds', nb)
print('ms     samples/build  idle%  ingest sah emit leaf other (% of bucket)')
for b in sorted(hist):
    h = hist[b]; n = sum(h.values())
    print(f"{b*B*1e3:5.1f}  {n/nb:6.1f}  {100*h['idle']/n:5.1f}  " + ' '.join(f"{100*h[c]/n:5.1f}" for c in ('ingest','sah','emit','leaf','other')))
