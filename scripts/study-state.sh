#!/usr/bin/env bash
# Carry a `pir2 train leap-cube` run across machines that do not keep `runs/` (a study longer
# than one sitting of a machine): `save` copies what `--resume` needs into a folder that is
# committed; `restore` puts it back into a run directory on the next machine, and training
# continues there with `--resume`, bit for bit as if it had not stopped (on the same kind of
# CPU; README, "Leap-cube demonstrations").
#
#   scripts/study-state.sh save RUN_DIR STATE_DIR
#   scripts/study-state.sh restore STATE_DIR RUN_DIR
#
# Stop the training before `save` (SIGINT or SIGTERM: each run writes `interrupted-NNNNNN/` at
# the step it reached and flushes its loss log to that step); a state saved from a running or
# killed process resumes from its last step checkpoint, and the steps logged after it are
# logged again.
#
# What is kept of RUN_DIR: its top-level files (config.toml, data.json), and per run
# (policy x seed folder) its files (loss.jsonl, ...), its `best/` once the run has finished,
# otherwise its newest resumable checkpoint (`step-NNNNNN` or `interrupted-NNNNNN`: weights,
# optimiser moments, EMA, the best pick so far, the batch generator's state). A run holds
# about 100 MB (U-Net [64, 128, 256] with per-position heads) until it has finished, 25 MB after.
# To keep each save's commit small (a replaced state counts twice in a push: the old files
# removed, the new ones added), a study longer than a sitting trains one run at a time
# (`pir2 train leap-cube --policy P --seeds S`), so one save replaces one run's state.
#
# `save` replaces STATE_DIR's content; it refuses a STATE_DIR that it did not write (no
# `STATE` file in it), so nothing else is overwritten. `restore` refuses a RUN_DIR that holds
# anything already.
set -euo pipefail

die() {
    echo "study-state: $*" >&2
    exit 1
}

# The newest resumable checkpoint of a run folder (by step number), or nothing.
newest() {
    local run="$1" best="" best_step=-1 d step
    for d in "$run"/step-* "$run"/interrupted-*; do
        [ -f "$d/train_state.json" ] || continue
        step="${d##*-}"
        step=$((10#$step))
        if [ "$step" -gt "$best_step" ]; then
            best_step=$step
            best="$d"
        fi
    done
    [ -n "$best" ] && echo "$best"
    return 0
}

save() {
    local run_dir="$1" state="$2"
    [ -f "$run_dir/config.toml" ] || die "$run_dir is not a training run (no config.toml)"
    if [ -e "$state" ] && [ -n "$(ls -A "$state")" ] && [ ! -f "$state/STATE" ]; then
        die "$state holds files this script did not write (no STATE file): not overwritten"
    fi
    local tmp="$state.tmp-$$"
    rm -rf "$tmp"
    mkdir -p "$tmp"
    find "$run_dir" -maxdepth 1 -type f -exec cp -p {} "$tmp/" \;
    local summary=() run name ckpt
    for run in "$run_dir"/*/; do
        run="${run%/}"
        name="$(basename "$run")"
        mkdir -p "$tmp/$name"
        find "$run" -maxdepth 1 -type f -exec cp -p {} "$tmp/$name/" \;
        if [ -d "$run/best" ]; then
            cp -rp "$run/best" "$tmp/$name/best"
            summary+=("$name finished (best/)")
        else
            ckpt="$(newest "$run")"
            if [ -n "$ckpt" ]; then
                cp -rp "$ckpt" "$tmp/$name/"
                # An interrupted state's model.safetensors is the `param/` tensors of its
                # train_state.safetensors, and `--resume` reads only the latter: 25 MB a run
                # not carried. (A step checkpoint keeps it: the best-of-last cells read it.)
                case "$(basename "$ckpt")" in
                interrupted-*) rm -f "$tmp/$name/$(basename "$ckpt")/model.safetensors" ;;
                esac
                summary+=("$name resumes from $(basename "$ckpt")")
            else
                summary+=("$name has no checkpoint yet (starts over)")
            fi
        fi
    done
    printf '%s\n' "${summary[@]}" > "$tmp/STATE"
    rm -rf "$state"
    mv "$tmp" "$state"
    cat "$state/STATE"
}

restore() {
    local state="$1" run_dir="$2"
    [ -f "$state/STATE" ] || die "$state is not a saved study state (no STATE file)"
    if [ -e "$run_dir" ] && [ -n "$(ls -A "$run_dir")" ]; then
        die "$run_dir is not empty: not overwritten (restore into a new directory)"
    fi
    mkdir -p "$run_dir"
    cp -rp "$state"/. "$run_dir"/
    rm -f "$run_dir/STATE"
    cat "$state/STATE"
}

case "${1:-}" in
save) [ $# -eq 3 ] || die "usage: $0 save RUN_DIR STATE_DIR"; save "$2" "$3" ;;
restore) [ $# -eq 3 ] || die "usage: $0 restore STATE_DIR RUN_DIR"; restore "$2" "$3" ;;
*) die "usage: $0 save RUN_DIR STATE_DIR | restore STATE_DIR RUN_DIR" ;;
esac
