"""Export a trained ``pir2_flow`` policy to a checkpoint pir2 runs with ONNX Runtime.

    python -m lerobot_policy_pir2_flow.export \\
        --policy-path OUTPUT/checkpoints/last/pretrained_model --out DIR
    pir2 eval ballplate --checkpoint DIR --policy pir2

``--policy-path`` is a directory ``lerobot-train`` saved (``config.json``,
``model.safetensors``, ``policy_postprocessor.json`` and its state). ``DIR`` (new) gets pir2's
ONNX checkpoint:

    DIR/model.onnx     x [B,H,A], tau [B,H], obs_fast [B,n_obs,F] (raw; normalised inside),
                       obs_slow [B,S] (raw), d_vis [B] (int64) -> v [B,H,A] (normalised units)
    DIR/stats.json     pir2's statistics: fast, fast_diff, slow (the network's) and action
                       (the affine map of the policy's LeRobot postprocessor)
    DIR/identity.json  the pir2 policy the schedule draws were of, SHA-256 of model.onnx
"""

from __future__ import annotations

import argparse
import pathlib

import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import FeatureType, NormalizationMode
from lerobot.processor import PolicyProcessorPipeline, UnnormalizerProcessorStep
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import ACTION, POLICY_POSTPROCESSOR_DEFAULT_NAME

from .configuration_pir2_flow import Pir2FlowConfig
from .flow import cli_policy_name, example_inputs, export_checkpoint
from .modeling_pir2_flow import Pir2FlowPolicy


def load_policy(path) -> Pir2FlowPolicy:
    """The trained policy at ``path``, on the CPU, in eval mode."""
    path = pathlib.Path(path)
    if not (path / "config.json").is_file():
        raise FileNotFoundError(f"{path} has no config.json: --policy-path must be a saved "
                                "policy (e.g. OUTPUT/checkpoints/last/pretrained_model)")
    config = PreTrainedConfig.from_pretrained(path)
    if not isinstance(config, Pir2FlowConfig):
        raise ValueError(f"{path} holds a {config.type!r} policy, not pir2_flow")
    config.device = "cpu"
    policy = Pir2FlowPolicy.from_pretrained(path, config=config)
    policy._require_stats()
    return policy


def action_affine(path, action_dim: int) -> dict:
    """``{"mean", "std"}`` such that ``action = v·std + mean`` is what the policy's saved
    LeRobot postprocessor does to an action in normalised units (every mode it supports is
    affine per dimension)."""
    pipe = PolicyProcessorPipeline.from_pretrained(
        pretrained_model_name_or_path=str(path),
        config_filename=f"{POLICY_POSTPROCESSOR_DEFAULT_NAME}.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )
    steps = [s for s in pipe.steps if isinstance(s, UnnormalizerProcessorStep)]
    if len(steps) != 1:
        raise ValueError(f"{path}: the postprocessor has {len(steps)} unnormaliser steps, "
                         "expected one")
    step = steps[0]
    mode = NormalizationMode(step.norm_map.get(FeatureType.ACTION, NormalizationMode.IDENTITY))
    flat = {k: v.double() for k, v in step.state_dict().items()}
    stats = {k.split(".", 1)[1]: v for k, v in flat.items() if k.startswith(ACTION + ".")}

    def need(*names):
        missing = [n for n in names if n not in stats]
        if missing:
            raise ValueError(f"{path}: the postprocessor's {mode.value} unnormalisation of "
                             f"{ACTION!r} has no {', '.join(missing)} statistics")
        return [stats[n] for n in names]

    def span(lo, hi):  # LeRobot's [-1, 1] modes: x = (v + 1)/2·(hi − lo) + lo
        d = hi - lo
        d = torch.where(d == 0, torch.full_like(d, step.eps), d)
        return {"mean": lo + d / 2, "std": d / 2}

    if mode is NormalizationMode.IDENTITY or ACTION not in step.features:
        affine = {"mean": torch.zeros(action_dim), "std": torch.ones(action_dim)}
    elif mode is NormalizationMode.MEAN_STD:
        mean, std = need("mean", "std")  # LeRobot unnormalises with std (the eps is on the way in)
        affine = {"mean": mean, "std": std}
    elif mode is NormalizationMode.MIN_MAX:
        affine = span(*need("min", "max"))
    elif mode is NormalizationMode.QUANTILES:
        affine = span(*need("q01", "q99"))
    elif mode is NormalizationMode.QUANTILE10:
        affine = span(*need("q10", "q90"))
    else:
        raise ValueError(f"{path}: unsupported action normalisation {mode.value}")
    out = {k: v.float().reshape(-1).tolist() for k, v in affine.items()}
    for k, v in out.items():
        if len(v) != action_dim:
            raise ValueError(f"{path}: the action {k} has {len(v)} values, the policy's "
                             f"action has {action_dim}")
    return out


def export(policy_path, out, seed: int = 0) -> tuple[float, str]:
    """Write the ONNX checkpoint of the policy at ``policy_path`` to ``out``; returns the
    largest |ONNX Runtime − torch| difference on the check inputs and the pir2 policy."""
    policy = load_policy(policy_path)
    cfg = policy.config
    stats = {**policy.model.stats(), "action": action_affine(policy_path, cfg.action_dim)}
    example = example_inputs(policy.model, batch=4, seed=seed)
    err = export_checkpoint(policy.model, out, cfg.policy, stats, example=example)
    return err, cfg.policy


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python -m lerobot_policy_pir2_flow.export",
        description="Export a trained pir2_flow policy to pir2's ONNX checkpoint "
                    "(model.onnx, stats.json, identity.json).")
    p.add_argument("--policy-path", required=True,
                   help="saved policy directory, e.g. OUTPUT/checkpoints/last/pretrained_model")
    p.add_argument("--out", required=True, help="output directory (must not exist)")
    p.add_argument("--seed", type=int, default=0, help="seed of the ONNX check inputs")
    args = p.parse_args(argv)
    err, policy = export(args.policy_path, args.out, seed=args.seed)
    print(f"ONNX Runtime matches torch (max |diff| {err:.2e}); wrote {args.out}/model.onnx, "
          f"stats.json, identity.json; run it with\n"
          f"  pir2 eval ballplate --checkpoint {args.out} --policy {cli_policy_name(policy)}")


if __name__ == "__main__":
    main()
