# suite scenes on the GPU and the device machine's CPU, scores side by side
for s in suite-56-5 suite-55-16 suite-97-8; do
  for d in cuda cpu; do
    t0=$(date +%s.%N)
    timeout 120 python3 -m torchproj.cli run $s --device $d --out /tmp/sg/$s-$d > /tmp/sg-$s-$d.log 2>&1
    rc=$?
    echo "$s $d rc=$rc $(python3 -c "print(round($(date +%s.%N)-$t0,1))") s"
    [ $rc = 0 ] || tail -5 /tmp/sg-$s-$d.log
    python3 -c "import json, sys; r = json.load(open(sys.argv[1])); print('  ', [(t['name'], round(t['psnr_db'], 2), round(t['ssim'], 3)) for t in r['targets']], {k: round(v, 2) for k, v in r.get('timings_s', {}).items()})" /tmp/sg/$s-$d/report.json 2>&1 | tail -1
  done
done
