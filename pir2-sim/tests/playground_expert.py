"""Reference side of tests/playground_expert.rs (run by the Rust test with $PIR2_PYTHON).

Usage: playground_expert.py DIR SEED

Builds a small ONNX graph shaped like MuJoCo Playground's published LeapCubeReorient policy
(normalise, swish MLP, Split, tanh), with seeded random weights, into DIR/policy.onnx; then
rolls it with onnxruntime over a sequence of observations built the playground's way
(goal-relative orientation from MuJoCo's quaternion functions, nearest blue-side-up goal,
previous action appended) and writes DIR/cases.json: per step the paper's 41-d observation
(fast 32, slow 9: rows 2-3 of the absolute rotation) and onnxruntime's action.
"""
import json
import sys

import mujoco
import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

out, seed = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(seed)
sizes = [57, 24, 20, 32]


def const(name, arr):
    return numpy_helper.from_array(np.asarray(arr, np.float32), name)


inits = [const("mean", rng.normal(0, 0.3, 57)), const("recip", rng.uniform(0.5, 3.0, 57))]
nodes = [helper.make_node("Sub", ["obs", "mean"], ["x0"]), helper.make_node("Mul", ["x0", "recip"], ["h0"])]
prev = "h0"
for k in range(len(sizes) - 1):
    w = rng.normal(0, 1.0 / np.sqrt(sizes[k]), (sizes[k], sizes[k + 1]))
    b = rng.normal(0, 0.1, sizes[k + 1])
    inits += [const(f"w{k}", w), const(f"b{k}", b)]
    nodes.append(helper.make_node("Gemm", [prev, f"w{k}", f"b{k}"], [f"g{k}"]))
    if k < len(sizes) - 2:
        nodes.append(helper.make_node("Sigmoid", [f"g{k}"], [f"s{k}"]))
        nodes.append(helper.make_node("Mul", [f"g{k}", f"s{k}"], [f"h{k + 1}"]))
        prev = f"h{k + 1}"
nodes.append(helper.make_node("Split", [f"g{len(sizes) - 2}"], ["loc", "scale"], axis=1, num_outputs=2))
nodes.append(helper.make_node("Tanh", ["loc"], ["continuous_actions"]))
graph = helper.make_graph(
    nodes,
    "policy",
    [helper.make_tensor_value_info("obs", TensorProto.FLOAT, [1, 57])],
    [helper.make_tensor_value_info("continuous_actions", TensorProto.FLOAT, [1, 16])],
    inits,
)
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
onnx.checker.check_model(model)
onnx.save(model, f"{out}/policy.onnx")
sess = ort.InferenceSession(f"{out}/policy.onnx", providers=["CPUExecutionProvider"])

goals = [np.array([0.0, np.cos(p / 2), np.sin(p / 2), 0.0]) for p in (0, np.pi / 2, np.pi, 1.5 * np.pi)]


def rows23(q):
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, q)
    return m[3:]


def rel(q, g):
    inv = np.zeros(4)
    mujoco.mju_negQuat(inv, g)
    d = np.zeros(4)
    mujoco.mju_mulQuat(d, q, inv)
    return d


cases = []
last = np.zeros(16, np.float32)
for t in range(40):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    fast = rng.normal(0, 0.5, 32)
    pos = rng.normal(0, 0.03, 3)
    errs = [2 * np.arcsin(min(np.linalg.norm(rel(q, g)[1:]), 1.0)) for g in goals]
    g = goals[int(np.argmin(errs))]
    obs = np.concatenate([fast, pos, rows23(rel(q, g)), last]).astype(np.float32)
    a = sess.run(None, {"obs": obs[None]})[0][0]
    cases.append({"fast": fast.tolist(), "slow": np.concatenate([pos, rows23(q)]).tolist(), "action": a.tolist()})
    last = a.astype(np.float32)
json.dump({"cases": cases}, open(f"{out}/cases.json", "w"))
