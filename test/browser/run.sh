#!/usr/bin/env bash
# End-to-end tests of the operator panel in Debian's headless chromium, driven by npm
# playwright-core: builds the apps, compiles the scripted demo cell, runs the tests
# (each starts what it needs and stops it), keeps screenshots in artifacts/. The last
# line is the summary `browser: N passed, M failed'.
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
top=$(cd "$here/../.." && pwd)
export ERL_LIBS="$top/_debdeps"
export CELLRT_TOP="$top"
cd "$top"

summary() { echo "browser: $1 passed, $2 failed"; }

if ! rebar3 compile >/dev/null; then
    echo "the apps do not compile"; summary 0 1; exit 1
fi
out="$top/_build/browser"
rm -rf "$out" "$here/artifacts"
mkdir -p "$out/ebin" "$here/artifacts"
paths=()
for d in "$top"/_build/default/lib/*/ebin; do paths+=(-pa "$d"); done
if ! erlc "${paths[@]}" -o "$out/ebin" "$top"/apps/cell_web/test/cell_web_demo.erl \
        "$top"/apps/cell_web/test/cell_web_demo_task.erl \
        "$top"/apps/cell_web/test/cell_web_router_demo.erl \
        "$top"/apps/cell_inspect/test/cell_inspect_demo.erl; then
    echo "the demo cell does not compile"; summary 0 1; exit 1
fi
if [ ! -d "$here/node_modules/playwright-core" ]; then
    (cd "$here" && npm ci --silent --no-audit --no-fund) || { summary 0 1; exit 1; }
fi
export CELLRT_BROWSER_EBIN="$out/ebin" CELLRT_BROWSER_ROOT="$out/root"
node --test --test-reporter=tap --test-concurrency=1 "$here"/*.test.mjs | tee "$out/tap.txt"
rc=${PIPESTATUS[0]}
pass=$(grep -oE '^# pass [0-9]+' "$out/tap.txt" | awk '{print $3}' | tail -1)
fail=$(grep -oE '^# fail [0-9]+' "$out/tap.txt" | awk '{print $3}' | tail -1)
pass=${pass:-0}
fail=${fail:-1}
[ "$rc" -ne 0 ] && [ "$fail" -eq 0 ] && fail=1
summary "$pass" "$fail"
[ "$fail" -eq 0 ]
