# Noiseless suite scenes (suite-56-5, suite-55-16, suite-97-8 with camera: noise removed, beside this) on the GPU and the machine's CPU: with no noise the two must agree
cd "$(dirname "$0")"  # the quiet-*.yaml beside this script
for s in quiet-56-5 quiet-55-16 quiet-97-8; do
  for d in cuda cpu; do
    timeout 100 python3 -m torchproj.cli run $s.yaml --device $d --no-cache --out /tmp/q/$s-$d > /tmp/q-$s-$d.log 2>&1
    echo "$s $d rc=$?"
    python3 -c "import json, sys; r = json.load(open(sys.argv[1])); print('  ', [(t['name'], round(t['psnr_db'], 3), round(t['ssim'], 4)) for t in r['targets']], {k: round(v, 2) for k, v in r.get('timings_s', {}).items()})" /tmp/q/$s-$d/report.json 2>&1 | tail -1
  done
done
tar czf $OUT/quiet_patterns.tgz -C /tmp q
