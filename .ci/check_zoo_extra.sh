#!/usr/bin/env bash
# The zoo extra, as a user gets it: build the wheel, install it with only the [zoo] extra into a fresh venv outside
# the repository, and run every command docs/zoo.md shows, at a tiny budget. Exits non-zero at the first failure.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
py="$work/venv/bin/python"
"$py" -m pip install --quiet "${TORCH:-torch==2.13.0}"  # the CPU build first, as the README says
"$py" -m pip wheel --quiet --no-deps -w "$work/dist" "$repo"
wheel="$(ls "$work"/dist/sb3_nfq-*.whl)"
# The package's one hyperparameter file is its only YAML (the benchmark's named configs stay in the repository)
"$py" -c 'import sys, zipfile; yml = [n for n in zipfile.ZipFile(sys.argv[1]).namelist() if n.endswith((".yml", ".yaml"))]
assert yml == ["sb3_nfq/hyperparams/nfq.yml"], yml' "$wheel"
"$py" -m pip install --quiet "$wheel[zoo]"
cd "$work"
export OMP_NUM_THREADS=1 SDL_VIDEODRIVER=dummy  # enjoy renders with pygame: no display here
run() { echo "+ $*"; "$@" > "$work/last.log" 2>&1 || { cat "$work/last.log"; exit 1; }; }
zoo() { run "$py" -m sb3_nfq.zoo "$@"; }
tiny=(--hyperparams gradient_steps:2)

zoo --help
zoo train --env CartPole-v1 -n 2048 "${tiny[@]}"
zoo train --env CartPole-v1 -n 4096 --eval-freq 2048 --eval-episodes 2 --save-freq 2048 -tb runs/ \
    --num-threads 1 --seed 0 "${tiny[@]}"
zoo train --env CartPole-v1 -n 2048 --hyperparams gradient_steps:2 loss:"'huber'"
zoo enjoy --env CartPole-v1 -n 200
zoo enjoy --env CartPole-v1 -n 200 --no-render --deterministic --exp-id 2 --load-best
zoo enjoy --env CartPole-v1 -n 200 --no-render -f logs --exp-id 2 --load-checkpoint 2048
zoo train --env CartPole-v1 -optimize --n-trials 2 -n 2048 --n-evaluations 1 --eval-episodes 2 --sampler tpe \
    --pruner median --num-threads 1 --no-optim-plots
zoo train --env CartPole-v1 -optimize --n-trials 2 -n 2048 --n-evaluations 1 --eval-episodes 2 \
    --storage study.log --study-name nfq-cartpole --seed 1 -f logs/worker1 --num-threads 1 --no-optim-plots
run "$work/venv/bin/optuna" trials --storage study.log --storage-class JournalFileBackend --study-name nfq-cartpole
run "$work/venv/bin/optuna" best-trial --storage study.log --storage-class JournalFileBackend --study-name nfq-cartpole
zoo train --env CartPole-v1 -n 2048 --storage study.log --study-name nfq-cartpole --trial-id 1
run "$work/venv/bin/optuna" create-study --storage sqlite:///nfq_study.db --study-name nfq-cartpole \
    --direction maximize --skip-if-exists
run "$py" -c 'from sb3_nfq import NFQ; print(NFQ.load("logs/nfq/CartPole-v1_1/CartPole-v1.zip").num_timesteps)'
test -s logs/nfq/CartPole-v1_2/best_model.zip && test -s logs/nfq/CartPole-v1_2/rl_model_2048_steps.zip
ls logs/nfq/report_CartPole-v1_*.csv > /dev/null && ls runs/CartPole-v1/NFQ_1 > /dev/null
echo "zoo extra: every documented command ran"
