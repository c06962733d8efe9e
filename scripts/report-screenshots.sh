#!/usr/bin/env bash
# The README's two pictures of the build report: the demo's, and that of a motorway exit (a map
# generated with PyPI roadgen, driven by `lidar2xodr simulate`, built with `lidar2xodr build`),
# opened zoomed to the demo's first lane-count change and to the exit's first junction. Needs headless Chromium (Debian package chromium).
# Usage: scripts/report-screenshots.sh [WORK_DIR]   (writes docs/report-demo.png, docs/report-junction.png)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
py="${PYTHON:-$root/.venv/bin/python}"
work="${1:-$(mktemp -d)}"
mkdir -p "$work" "$root/docs"
cd "$work"
[ -f demo/report/index.html ] || "$py" -m lidar2xodr.cli demo --out demo
if [ ! -f exit/report/index.html ]; then
  "$py" - <<'EOF'
import roadgen

m = roadgen.Map(name="exit")
corridor = m.add_corridor("A1", [(0.0, 0.0, 0.0), (1200.0, 0.0, 0.0), (2000.0, 150.0, 0.0)], lanes=3)
corridor.add_ramp("exit1", at=700.0, end=(1200.0, -250.0, 0.0), side="right", on=False)
m.add_plan(corridor.plan())
m.export_opendrive("exit.xodr", trace=False)
EOF
  "$py" -m lidar2xodr.cli simulate exit.xodr exit-drive --start-road 1 --traffic low
  "$py" -m lidar2xodr.cli build exit-drive -o exit/map.xodr --report exit/report --reference exit.xodr
fi
shot() {
  local flags=(--headless --disable-gpu --hide-scrollbars --window-size=1400,900 --virtual-time-budget=10000)
  [ "$(id -u)" -eq 0 ] && flags+=(--no-sandbox)
  chromium "${flags[@]}" --screenshot="$2" "file://$work/$1" 2>/dev/null
}
shot "demo/report/index.html#map=lanes" "$root/docs/report-demo.png"
shot "exit/report/index.html#map=junction" "$root/docs/report-junction.png"
ls -l "$root/docs/report-demo.png" "$root/docs/report-junction.png"
