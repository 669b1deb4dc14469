#!/bin/bash
# Leave one real source out: fine-tune the front-end checkpoint on the other real sets' graphs
# (plus simulator graphs to keep the paper regime) and evaluate on the held-out set's test
# graphs (research/frontend_refiner/README.md, "Fine-tuning on real sets"). The training
# graphs: /tmp/realtrain_<set> (TrainSplit layouts of real_layout.py's sets), /tmp/fe_sim
# (posernet-make-data dataset=paper, 200 train / 20 val graphs per scene). Selection rule,
# fixed before any evaluation: the last of 8 epochs at lr 1e-4.
set -e
cd "$(dirname "$0")/../.."
F=$PWD/src/posernet/checkpoints/posernet_frontend_kp.ckpt
declare -A ROOTS
ROOTS[kitchen]="/tmp/realtrain_squirrel,/tmp/realtrain_fountain,/tmp/realtrain_herzjesu,/tmp/fe_sim"
ROOTS[squirrel]="/tmp/realtrain_redkitchen,/tmp/realtrain_redkitchenwide,/tmp/realtrain_fountain,/tmp/realtrain_herzjesu,/tmp/fe_sim"
ROOTS[fountain]="/tmp/realtrain_redkitchen,/tmp/realtrain_redkitchenwide,/tmp/realtrain_squirrel,/tmp/realtrain_herzjesu,/tmp/fe_sim"
ROOTS[herzjesu]="/tmp/realtrain_redkitchen,/tmp/realtrain_redkitchenwide,/tmp/realtrain_squirrel,/tmp/realtrain_fountain,/tmp/fe_sim"
for fold in kitchen squirrel fountain herzjesu; do
  .venv/bin/posernet-train "data.root=[${ROOTS[$fold]}]" model=adaptive model.net.depth=3 \
    model.net.node_hidden=64 model.net.mlp_hidden=64 \
    "data.init_mix={kp: 0.4, bb: 0.3, gt: 0.2, recorrupt: 0.1}" trainer.max_epochs=8 seed=0 \
    model.loss.harm=0.2 model.loss.harm_scale=0.0175 model.optimizer.lr=1e-4 init_from=$F \
    hydra.run.dir=/tmp/loso_$fold test_after_training=false
done
for pair in kitchen:redkitchen kitchen:redkitchenwide squirrel:squirrel fountain:fountain herzjesu:herzjesu; do
  .venv/bin/python research/adaptive.py --data /tmp/realdata_${pair##*:} --model frontend=$F \
    --model loso=/tmp/loso_${pair%%:*}/checkpoints/last.ckpt --out /tmp/eval_loso_${pair##*:}
done
