#!/usr/bin/env bash
# How the agent shipped in src/tsnav/agent/weights/ was made (issue 23 section 4). Every step is resumable and
# skipped when its output exists; run it again after an interruption. About 3 hours of the 2-core machine.
#
#   bash scripts/train_release_agent.sh WORK_DIR [NAME]                  # the default agent, RECIPE=learned7
#   RECIPE=learned6 bash scripts/train_release_agent.sh WORK_DIR tsrm-demae-learned6
#   RECIPE=learned4 bash scripts/train_release_agent.sh WORK_DIR tsrm-demae-learned4-v2
#
# WORK_DIR gets the 120-room world (30 GB at 128 px), the pretraining run, the training run and the evaluations;
# the packed agent is written to src/tsnav/agent/weights/NAME (default: the recipe's name).
# RECIPE picks the agent: learned4 (tsrm-demae-learned4-v2), learned6 (tsrm-demae-learned6: the shipped learned6
# detector's tables, --blocked-action, seed 3) or learned7 (the default: tsrm-demae-learned7, the shipped default; learned7's
# tables, --blocked-action, seed 3, and the checkpoint chosen afterwards on 2000 val episodes instead of the training's
# 400). The shipped runs were trained in legs resumed in the same folder (learned4: 2000, 3000, 4000 updates;
# learned6 and learned7: 2000, then 4000); this script runs one leg to 4000.
# The learning rate is constant and the trainer resumes bit for bit (tested), so one run to 4000 updates should give
# the same agent on this machine (not re-run here for either recipe).
set -euo pipefail
W=${1:?usage: train_release_agent.sh WORK_DIR [NAME]}
RECIPE=${RECIPE:-learned7}
SELECT=
case "$RECIPE" in
  learned4) NAME=${2:-tsrm-demae-learned4-v2}; DET=learned4; SEED=1; FLAGS=(); CARD=release_card.json; CONV=conv ;;
  learned6) NAME=${2:-tsrm-demae-learned6}; DET=learned6; SEED=3; FLAGS=(--blocked-action); CARD=release_card_learned6.json
            CONV=conv-learned6 ;;
  learned7) NAME=${2:-tsrm-demae-learned7}; DET=learned7; SEED=3; FLAGS=(--blocked-action); CARD=release_card_learned7.json
            CONV=conv-learned7; SELECT=500 ;;
  *) echo "RECIPE must be learned4, learned6 or learned7, got $RECIPE" >&2; exit 2 ;;
esac
HERE="$(cd "$(dirname "$0")/.." && pwd)"
T="$HERE/.venv/bin/tsnav"
PY="$HERE/.venv/bin/python"
mkdir -p "$W"
# 1. the 120 real iTHOR rooms at 128x128 with the rules the agent was trained on (version 2, the default)
"$T" world --preset ithor-real --world-version 2 --out "$W/real128" --workers 2
# 2. the recipe's shipped detector's tables (its confidence drives the stage switch, paper III-B)
"$T" detect --data "$W/real128" --detector shipped --shipped "$DET" --name "$DET" --threads 1 --quiet
# 3. DE-MAE pretraining at the medium scale (ViT-Tiny, 64 px, patch 16, 800 steps of 64 frames) and its features
"$PY" - "$W" <<'EOF'
import sys
from pathlib import Path
from tsnav.distributed import set_threads
from tsnav.pipeline.steps import EncoderSpec, ensure_encoder, ensure_features
set_threads(1)  # the shipped encoder was pretrained and its features cached on one thread
w = Path(sys.argv[1])
pre = dict(method="demae", model="vit_tiny", patch_size=16, img_size=64, steps=800, batch_size=64, base_lr=1.5e-3,
           device="cpu")
es = EncoderSpec("demae", str(w / "pre" / "demae-p16"), "vit_tiny", 16, 64, pre)
ensure_encoder(es, w / "real128")
name = ensure_features(es, w / "real128", ["train", "val", "test"], batch_size=128, device="cpu")
(w / "features.txt").write_text(name + "\n")
EOF
F=$(cat "$W/features.txt")
# 4. TSRM training under the lineage success protocol with the batched trainer (256 episodes x 30 steps per update, lr 1e-3, cpu preset), every 250
#    updates scored greedily on 400 val episodes; the best is RUN/best
"$T" convergence --data "$W/real128" --features "$F" --detections "$DET" --out "$W/$CONV" --updates 4000 \
  --chunk 250 --patience 6 --num-envs 256 --preset cpu --lr 1e-3 --seed "$SEED" --val-per-room-type 100 \
  --protocol lineage "${FLAGS[@]}"
# 4b. (learned7) score every milestone again on 2000 val episodes (500 per room type, another seed than the training's
#     400) in a copy of the run, RUN-select, whose best is packed (the run keeps the training's own selection, so a
#     second call of this script skips both)
RUN="$W/$CONV/run"
if [ -n "$SELECT" ]; then
  [ -e "$W/val_select_lineage.json" ] || "$T" episodes --data "$W/real128" --split val --per-room-type "$SELECT" --seed 1 \
    --protocol lineage --out "$W/val_select_lineage.json"
  if [ ! -e "$W/$CONV/run-select" ]; then
    rm -rf "$W/$CONV/run-select.tmp"
    cp -r "$RUN" "$W/$CONV/run-select.tmp" && mv "$W/$CONV/run-select.tmp" "$W/$CONV/run-select"
  fi
  RUN="$W/$CONV/run-select"
  "$T" select --run "$RUN" --data "$W/real128" --episodes "$W/val_select_lineage.json"
fi
# 5. pack (policy, float16 encoder, model card; skipped when the folder exists, as the shipped one does: pass another
#    NAME to pack a new agent beside it) and write the val and test figures into the card
if [ ! -e "$HERE/src/tsnav/agent/weights/$NAME" ]; then
  "$T" release pack --run "$RUN" --encoder-run "$W/pre/demae-p16" --card "$HERE/scripts/$CARD" \
    --out "$HERE/src/tsnav/agent/weights/$NAME"
fi
"$T" release eval --agent "$NAME" --split val --data "$W/real128" --out "$W/release_val" --update-card --threads 1
"$T" release eval --agent "$NAME" --split test --data "$W/real128" --out "$W/release_test" --update-card --threads 1
