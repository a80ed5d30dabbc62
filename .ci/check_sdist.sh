#!/usr/bin/env bash
# The sdist, as a packager gets it: build it, unpack it outside the repository, and run its own fast tests there
# (with the dev environment's packages; the unpacked sb3_nfq is the one imported).
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
py="${PYTHON:-$repo/.venv/bin/python}"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
"$py" -m build --sdist --no-isolation --outdir "$work/dist" "$repo" > "$work/build.log" 2>&1 || { cat "$work/build.log"; exit 1; }
tar -xzf "$work"/dist/sb3_nfq-*.tar.gz -C "$work"
cd "$work"/sb3_nfq-*/
"$py" -c 'import sb3_nfq, pathlib, sys; sys.exit(0 if pathlib.Path(sb3_nfq.__file__).is_relative_to(pathlib.Path.cwd()) else 1)'
"$py" -m pytest -p no:cacheprovider -q -m "not slow" tests/test_fitting.py tests/test_bad_input.py tests/test_callbacks.py \
    tests/test_contract.py tests/test_examples.py -k "not offline_minari"
