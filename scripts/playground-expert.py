#!/usr/bin/env python3
"""Convert a MuJoCo Playground LeapCubeReorient policy (ONNX export) into a pir2 expert file.

Usage: playground-expert.py POLICY.onnx OUT.safetensors

The input is the policy MuJoCo Playground publishes for sim-to-sim transfer
(`mujoco_playground/experimental/sim2sim/onnx/leap_reorient_policy.onnx` in
github.com/google-deepmind/mujoco_playground, Apache-2.0): a TF graph exported by tf2onnx that
normalises the 57-d observation (`(x - mean) * recip`), runs a swish MLP and returns
`tanh` of the first half of the last layer (the Gaussian mean; the second half parameterises a
state-dependent scale, which a deterministic expert does not use).

The output is a `pir2-ppo-expert-v1` safetensors file (see `pir2_sim::leap::ppo::expert`):
`actor` (per layer the out x in row-major weight, then the bias), `obs_mean`, `obs_std`
(= 1 / recip), `log_std` (zeros: not carried), metadata `squash=tanh`,
`orientation=nearest_goal`, `obs_clip=none`, `prev_action=true`. The graph is checked node by
node; anything else is refused with one error naming what differs.

Needs the `onnx` and `numpy` packages. Writes atomically; refuses to overwrite an existing file.
"""
import json
import os
import struct
import sys

import numpy as np
import onnx
from onnx import numpy_helper

NU = 16
OBS = 57


def fail(msg):
    sys.exit(f"playground-expert: {msg}")


def convert(src):
    model = onnx.load(src)
    g = model.graph
    init = {i.name: numpy_helper.to_array(i) for i in g.initializer}
    nodes = list(g.node)
    if len(g.input) != 1 or len(g.output) != 1:
        fail(f"{src}: expected one input and one output, found {len(g.input)} and {len(g.output)}")
    ops = [n.op_type for n in nodes]
    if ops[:2] != ["Sub", "Mul"] or ops[-2:] != ["Split", "Tanh"]:
        fail(f"{src}: unexpected graph {ops} (expected Sub, Mul, [Gemm, Sigmoid, Mul]*, Gemm, Split, Tanh)")
    mean = init.get(nodes[0].input[1])
    recip = init.get(nodes[1].input[1])
    if mean is None or recip is None or mean.shape != (OBS,) or recip.shape != (OBS,):
        fail(f"{src}: the normaliser is not two {OBS}-vectors")
    if not np.all(recip > 0):
        fail(f"{src}: the normaliser has non-positive scales")
    body = ops[2:-2]
    layers = []
    k = 2
    while k < len(nodes) - 2:
        n = nodes[k]
        if n.op_type != "Gemm":
            fail(f"{src}: node {k} is {n.op_type}, expected Gemm")
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
        if attrs.get("transA", 0) or attrs.get("alpha", 1.0) != 1.0 or attrs.get("beta", 1.0) != 1.0:
            fail(f"{src}: Gemm {k} has unsupported attributes {attrs}")
        w = init[n.input[1]]
        if attrs.get("transB", 0):
            w = w.T
        layers.append((w, init[n.input[2]]))  # w: in x out
        if k + 1 < len(nodes) - 2:
            if [nodes[k + 1].op_type, nodes[k + 2].op_type] != ["Sigmoid", "Mul"]:
                fail(f"{src}: hidden layer {len(layers)} is not swish (Sigmoid, Mul)")
            k += 3
        else:
            k += 1
    if len(body) != 3 * len(layers) - 2:
        fail(f"{src}: unexpected graph {ops}")
    sizes = [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers]
    if sizes[0] != OBS or sizes[-1] != 2 * NU:
        fail(f"{src}: layer sizes {sizes}, expected {OBS} in and {2 * NU} out")
    split = [onnx.helper.get_attribute_value(a) for a in nodes[-2].attribute if a.name == "split"]
    if split and list(split[0]) != [NU, NU]:
        fail(f"{src}: Split {list(split[0])}, expected [{NU}, {NU}]")
    w_last, b_last = layers[-1]
    layers[-1] = (w_last[:, :NU], b_last[:NU])
    sizes[-1] = NU
    params = np.concatenate([np.concatenate([w.T.ravel(), b.ravel()]) for w, b in layers]).astype("<f4")
    tensors = {
        "actor": params,
        "obs_mean": mean.astype("<f4"),
        "obs_std": (1.0 / recip.astype(np.float64)).astype("<f4"),
        "log_std": np.zeros(NU, "<f4"),
    }
    meta = {
        "format": "pir2-ppo-expert-v1",
        "sizes": ",".join(str(s) for s in sizes),
        "activation": "silu",
        "prev_action": "true",
        "squash": "tanh",
        "orientation": "nearest_goal",
        "obs_clip": "none",
        "iteration": "0",
        "env_steps": "0",
        "source": os.path.basename(src),
    }
    return tensors, meta


def write_safetensors(path, tensors, meta):
    header = {"__metadata__": meta}
    off = 0
    blobs = []
    for name, arr in tensors.items():
        b = np.ascontiguousarray(arr).tobytes()
        header[name] = {"dtype": "F32", "shape": list(arr.shape), "data_offsets": [off, off + len(b)]}
        off += len(b)
        blobs.append(b)
    h = json.dumps(header, separators=(",", ":")).encode()
    h += b" " * (-len(h) % 8)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__.split("\n\n")[1])
    src, out = sys.argv[1], sys.argv[2]
    if not os.path.isfile(src):
        fail(f"{src}: no such file")
    if os.path.exists(out):
        fail(f"{out} exists; refusing to overwrite it")
    tensors, meta = convert(src)
    write_safetensors(out, tensors, meta)
    print(f"wrote {out}: sizes {meta['sizes']}, {tensors['actor'].size} parameters")


if __name__ == "__main__":
    main()
