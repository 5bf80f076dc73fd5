"""Tiny synthetic GR00T N1.7 ONNX graphs with the export contract's names and shapes.

Embedded in `pir2_backends::gr00t::testing` (used by pir2-backends/tests/gr00t.rs and the
pir2-cli tests; run with $PIR2_PYTHON, which has `onnx`). The
functions are small random MLP-like maps, chosen so that every input influences the
output; they are not GR00T. Usage:

    make_graphs.py OUTDIR [VARIANT [D_VL]]

VARIANT breaks one file on purpose: wrong_name, wrong_rank, wrong_dim, wrong_type.
"""

import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

H, A_MAX, S_MAX, D_IN, D_VL, D_HID, CROP, VOCAB, SLOTS = 50, 24, 64, 32, 24, 16, 16, 64, 32
N_OBS = 1
rng = np.random.default_rng(7)


def w(*shape, scale=0.3):
    return (rng.standard_normal(shape) * scale).astype(np.float32)


def save(path, nodes, inputs, outputs, inits):
    g = helper.make_graph(nodes, "g", inputs, outputs, [numpy_helper.from_array(v, k) for k, v in inits.items()])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)], producer_name="pir2-test")
    m.ir_version = 8
    onnx.checker.check_model(m)
    onnx.save(m, path)


def vi(name, ty, shape):
    return helper.make_tensor_value_info(name, ty, shape)


F, I, B = TensorProto.FLOAT, TensorProto.INT64, TensorProto.BOOL


def main(out, variant):
    # state encoder: tanh(state @ W) + slot[embodiment_id]
    save(
        f"{out}/state_encoder.onnx",
        [
            helper.make_node("MatMul", ["state", "W"], ["m"]),
            helper.make_node("Tanh", ["m"], ["t"]),
            helper.make_node("Gather", ["slots", "embodiment_id"], ["e"], axis=0),  # [B, D]
            helper.make_node("Unsqueeze", ["e", "ax1"], ["e1"]),
            helper.make_node("Add", ["t", "e1"], ["output"]),
        ],
        [vi("state", F, [1, 1, N_OBS * S_MAX]), vi("embodiment_id", I, [1])],
        [vi("output", F, [1, 1, D_IN])],
        {"W": w(N_OBS * S_MAX, D_IN), "slots": w(SLOTS, D_IN), "ax1": np.array([1], np.int64)},
    )

    # action encoder: actions @ W + (timesteps/1000)[..., None] * wt + slot[embodiment_id]
    ts_shape = [1] if variant == "wrong_rank" else [1, H]
    save(
        f"{out}/action_encoder.onnx",
        [
            helper.make_node("MatMul", ["actions", "W"], ["m"]),
            helper.make_node("Cast", ["timesteps"], ["tf"], to=F),
            helper.make_node("Div", ["tf", "k1000"], ["tn"]),
            helper.make_node("Unsqueeze", ["tn", "axm1"], ["tu"]),
            helper.make_node("Mul", ["tu", "wt"], ["te"]),
            helper.make_node("Add", ["m", "te"], ["s"]),
            helper.make_node("Gather", ["slots", "embodiment_id"], ["e"], axis=0),
            helper.make_node("Unsqueeze", ["e", "ax1"], ["e1"]),
            helper.make_node("Add", ["s", "e1"], ["output"]),
        ],
        [vi("actions", F, [1, H, A_MAX]), vi("timesteps", I, ts_shape), vi("embodiment_id", I, [1])],
        [vi("output", F, [1, H, D_IN])],
        {
            "W": w(A_MAX, D_IN),
            "wt": w(D_IN),
            "k1000": np.array(1000.0, np.float32),
            "axm1": np.array([-1], np.int64),
            "ax1": np.array([1], np.int64),
            "slots": w(SLOTS, D_IN),
        },
    )

    # DiT: tanh(sa @ Ws + mean_T(vl · mask) @ Wv + (timestep/1000)[..., None] * wt + mean_T(vl · img) @ Wi
    #           + sa[:, 0:1] @ Wst)
    d_in = 16 if variant == "wrong_dim" else D_IN
    sa_name = "sa_emb" if variant == "wrong_name" else "sa_embs"
    save(
        f"{out}/dit.onnx",
        [
            helper.make_node("MatMul", [sa_name, "Ws"], ["a"]),
            helper.make_node("Cast", ["backbone_attention_mask"], ["mf"], to=F),
            helper.make_node("Unsqueeze", ["mf", "axm1"], ["mu"]),
            helper.make_node("Mul", ["vl_embs", "mu"], ["vm"]),
            helper.make_node("ReduceMean", ["vm", "ax1"], ["vmean"], keepdims=1),  # [1,1,D_VL]
            helper.make_node("MatMul", ["vmean", "Wv"], ["c"]),
            helper.make_node("Cast", ["image_mask"], ["if"], to=F),
            helper.make_node("Unsqueeze", ["if", "axm1"], ["iu"]),
            helper.make_node("Mul", ["vl_embs", "iu"], ["vi"]),
            helper.make_node("ReduceMean", ["vi", "ax1"], ["imean"], keepdims=1),
            helper.make_node("MatMul", ["imean", "Wi"], ["ci"]),
            helper.make_node("Cast", ["timestep"], ["tf"], to=F),
            helper.make_node("Div", ["tf", "k1000"], ["tn"]),
            helper.make_node("Unsqueeze", ["tn", "axm1"], ["tu"]),
            helper.make_node("Mul", ["tu", "wt"], ["te"]),
            helper.make_node("Add", ["a", "c"], ["s1"]),
            helper.make_node("Add", ["s1", "ci"], ["s2"]),
            helper.make_node("Add", ["s2", "te"], ["s3"]),
            # The state token (position 0) reaches every position, as attention would.
            helper.make_node("Slice", [sa_name, "z1", "o1", "ax1"], ["st"]),
            helper.make_node("MatMul", ["st", "Wst"], ["sc"]),
            helper.make_node("Add", ["s3", "sc"], ["s4"]),
            helper.make_node("Tanh", ["s4"], ["output"]),
        ],
        [
            vi(sa_name, F, [1, H + 1, d_in]),
            vi("vl_embs", F, [1, "T", D_VL]),
            vi("timestep", I, [1, H + 1]),
            vi("image_mask", B, [1, "T"]),
            vi("backbone_attention_mask", B, [1, "T"]),
        ],
        [vi("output", F, [1, H + 1, D_HID])],
        {
            "Ws": w(d_in, D_HID),
            "Wv": w(D_VL, D_HID),
            "Wi": w(D_VL, D_HID),
            "wt": w(D_HID),
            "Wst": w(d_in, D_HID),
            "k1000": np.array(1000.0, np.float32),
            "axm1": np.array([-1], np.int64),
            "ax1": np.array([1], np.int64),
            "z1": np.array([0], np.int64),
            "o1": np.array([1], np.int64),
        },
    )

    # action decoder: model_output @ W + slot[embodiment_id]
    out_ty = I if variant == "wrong_type" else F
    nodes = [
        helper.make_node("MatMul", ["model_output", "W"], ["m"]),
        helper.make_node("Gather", ["slots", "embodiment_id"], ["e"], axis=0),
        helper.make_node("Unsqueeze", ["e", "ax1"], ["e1"]),
        helper.make_node("Add", ["m", "e1"], ["o" if out_ty == I else "output"]),
    ]
    if out_ty == I:
        nodes.append(helper.make_node("Cast", ["o"], ["output"], to=I))
    save(
        f"{out}/action_decoder.onnx",
        nodes,
        [vi("model_output", F, [1, H + 1, D_HID]), vi("embodiment_id", I, [1])],
        [vi("output", out_ty, [1, H + 1, A_MAX])],
        {"W": w(D_HID, A_MAX, scale=0.5), "slots": w(SLOTS, A_MAX, scale=0.1), "ax1": np.array([1], np.int64)},
    )

    # backbone: embed[input_ids] * attention + pooled_pixels @ Wp, where the pixels of the
    # V views (`images`, first axis) are pooled order-sensitively (mean over views of their
    # running sum: earlier views weigh more), so a swapped view order changes the output;
    # with one view this is the plain pixel mean.
    save(
        f"{out}/backbone.onnx",
        [
            # ids wrap around the tiny table, so a real tokenizer's ids (fixture BPE: ~400) fit
            helper.make_node("Mod", ["input_ids", "vocab"], ["ids"]),
            helper.make_node("Gather", ["embed", "ids"], ["tok"], axis=0),  # [b,T,D_VL]
            helper.make_node("Cast", ["attention_mask"], ["af"], to=F),
            helper.make_node("Unsqueeze", ["af", "axm1"], ["au"]),
            helper.make_node("Mul", ["tok", "au"], ["tm"]),
            helper.make_node("ReduceMean", ["pixel_values", "ax23"], ["pm0"], keepdims=0),  # [V,3]
            helper.make_node("CumSum", ["pm0", "ax0s"], ["pc"]),  # [V,3]
            helper.make_node("ReduceMean", ["pc", "ax0"], ["pm"], keepdims=1),  # [1,3]
            helper.make_node("MatMul", ["pm", "Wp"], ["pv"]),  # [1,D_VL]
            helper.make_node("Unsqueeze", ["pv", "ax1"], ["pu"]),
            helper.make_node("Add", ["tm", "pu"], ["embeddings"]),
        ],
        [
            vi("pixel_values", F, ["images", 3, CROP, CROP]),
            vi("input_ids", I, ["batch", "T"]),
            vi("attention_mask", I, ["batch", "T"]),
        ],
        [vi("embeddings", F, ["batch", "T", D_VL])],
        {
            "embed": w(VOCAB, D_VL),
            "Wp": w(3, D_VL, scale=2.0),
            "vocab": np.array(VOCAB, np.int64),
            "axm1": np.array([-1], np.int64),
            "ax1": np.array([1], np.int64),
            "ax23": np.array([2, 3], np.int64),
            "ax0": np.array([0], np.int64),
            "ax0s": np.array(0, np.int64),
        },
    )

    # vl self-attention stand-in: hidden + tanh(hidden @ W)
    save(
        f"{out}/vl_self_attention.onnx",
        [
            helper.make_node("MatMul", ["hidden_states", "W"], ["m"]),
            helper.make_node("Tanh", ["m"], ["t"]),
            helper.make_node("Add", ["hidden_states", "t"], ["output"]),
        ],
        [vi("hidden_states", F, [1, "T", D_VL])],
        [vi("output", F, [1, "T", D_VL])],
        {"W": w(D_VL, D_VL)},
    )


if __name__ == "__main__":
    if len(sys.argv) > 3:
        # Another backbone width D_VL (e.g. to match a training fixture's head).
        D_VL = int(sys.argv[3])
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else "")
