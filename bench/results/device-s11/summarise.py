import json,sys,glob,collections,os
# Medians per round of the dragon rows of interleaved A/B runs: summarise.py DIR
rows=collections.defaultdict(list)
for f in sorted(glob.glob(sys.argv[1]+'/*.json')):
    d=json.load(open(f)); tag=os.path.basename(f).split('-',1)[1].rsplit('.',1)[0]
    for r in d['results']:
        if r['scene']!='dragon_vrip' or r['status']!='ok': continue
        rows[(r['workload'],r.get('threads'),tag)].append(r['median_ms'])
for k in sorted(rows):
    v=rows[k]; s=sorted(v)
    print(f"{k[0]:16} t{k[1]:>3} {k[2]:10} " + " ".join(f"{x:6.1f}" for x in v) + f"   median {s[len(s)//2]:6.1f}")
