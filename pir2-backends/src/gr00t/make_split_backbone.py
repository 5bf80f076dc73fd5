"""Tiny stand-ins for GR00T N1.7's split backbone export, and their fused composition.

Embedded in `pir2_backends::gr00t::testing` (`write_split_backbone`; run with $PIR2_PYTHON,
which has `onnx`). Writes, for one prompt sequence given in SPEC.json:

    OUTDIR/onnx/vit_fp32.onnx   pixel_values [P, 3·t·p²] -> image_embeds [N, D],
                                deepstack_features [3, N, D]       (GR00T's ViT signature)
    OUTDIR/onnx/llm_fp32.onnx   inputs_embeds [1, T, D], attention_mask [1, T] i64,
                                position_ids [3, 1, T] i64, visual_pos_masks [1, T] bool,
                                deepstack_0..2 [N, D] -> embeddings [1, T, D]  (GR00T's LLM)
    OUTDIR/model.safetensors    the token-embedding table (BF16) under KEY, plus one
                                unrelated tensor
    OUTDIR/fused_backbone.onnx  pixel_values [V, 3, s, s], input_ids, attention_mask ->
                                embeddings: the same maps composed in one graph, with the
                                patching, the embedding lookup and the image-token scatter as
                                ONNX ops and the positions of SPEC's sequence as a constant
    OUTDIR/position_ids.json    those positions, [3][T]

The maps are small random functions, not GR00T; the LLM stand-in depends on every position
id row, on the order of the tokens (a running sum stands in for causal attention), on the
padding mask and on the deepstack features at the visual positions, so a wrong glue changes
its output. The positions follow the public rule of transformers' Qwen3-VL `get_rope_index`
(transcribed below). VARIANT (comma-separated) changes the stand-ins:

    wrong_name        the LLM takes `input_embeds`
    wrong_width       the LLM takes inputs_embeds of width D - 4
    llm_bf16          `llm_bf16.onnx` (no llm_fp32.onnx) with bfloat16 inputs_embeds,
                      deepstack_* and embeddings, as GR00T's exporter writes it by default;
                      Casts at the boundary, the same float32 interior
    vit_bf16          `vit_bf16.onnx` (no vit_fp32.onnx) with bfloat16 pixel_values,
                      image_embeds and deepstack_features, likewise
    llm_f16           float16 boundary, still named `llm_fp32.onnx` (the file's declared
                      types decide, not its name)
    llm_f64           inputs_embeds declared float64 (not a type pir2 takes)
    llm_bf16_matmul   `llm_bf16.onnx` whose first op is a bfloat16 MatMul (no kernel on
                      ONNX Runtime's CPU provider)

    make_split_backbone.py SPEC.json OUTDIR [VARIANT[,VARIANT…]]
"""

import json
import struct
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

F, I, B = TensorProto.FLOAT, TensorProto.INT64, TensorProto.BOOL
BF16, F16, F64 = TensorProto.BFLOAT16, TensorProto.FLOAT16, TensorProto.DOUBLE
DV, LAYERS, DEEPSTACK = 8, 4, 3
rng = np.random.default_rng(11)


def w(*shape, scale=0.4):
    return (rng.standard_normal(shape) * scale).astype(np.float32)


class Builder:
    def __init__(self, prefix):
        self.prefix, self.nodes, self.inits, self.k = prefix, [], {}, 0

    def const(self, name, arr):
        key = self.prefix + name
        self.inits[key] = np.asarray(arr)
        return key

    def op(self, ty, ins, out=None, **kw):
        self.k += 1
        out = out or f"{self.prefix}{ty.lower()}_{self.k}"
        self.nodes.append(helper.make_node(ty, ins, [out], **kw))
        return out


def scatter(g, base, mask, src, add):
    """base [1,T,D]; the k-th True of mask [1,T] takes (add: gets plus) src[k]."""
    mi = g.op("Cast", [mask], to=I)
    idx = g.op("Sub", [g.op("CumSum", [mi, g.const("ax1s", np.array(1, np.int64))]), g.const("one", np.array(1, np.int64))])
    idx = g.op("Max", [idx, g.const("zero_i", np.array(0, np.int64))])
    gathered = g.op("Gather", [src, idx], axis=0)
    mu = g.op("Unsqueeze", [mask, g.const("axm1", np.array([-1], np.int64))])
    if add:
        delta = g.op("Where", [mu, gathered, g.const("zero_f", np.array(0.0, np.float32))])
        return g.op("Add", [base, delta])
    return g.op("Where", [mu, gathered, base])


def vit(g, pv, p_rows, patch_dim, n, m2, d):
    h = g.op("Tanh", [g.op("Add", [g.op("MatMul", [pv, g.const("Wp", w(patch_dim, DV, scale=0.2))]), g.const("pos", w(p_rows, DV))])])
    merged = g.op("Reshape", [h, g.const("merge_shape", np.array([n, m2 * DV], np.int64))])
    img = g.op("MatMul", [merged, g.const("M", w(m2 * DV, d))])
    ds = []
    for l in range(DEEPSTACK):
        hl = g.op("Tanh", [g.op("MatMul", [h, g.const(f"L{l}", w(DV, DV, scale=0.8))])])
        ml = g.op("Reshape", [hl, g.const("merge_shape", np.array([n, m2 * DV], np.int64))])
        ds.append(g.op("MatMul", [ml, g.const(f"Md{l}", w(m2 * DV, d))]))
    return img, ds


def llm(g, emb, am, pos, vis, ds, d, out):
    amf = g.op("Cast", [am], to=F)
    amu = g.op("Unsqueeze", [amf, g.const("axm1", np.array([-1], np.int64))])
    posf = g.op("Cast", [pos], to=F)
    post = g.op("Transpose", [posf], perm=[1, 2, 0])  # [1, T, 3]
    pe = g.op("Sin", [g.op("MatMul", [post, g.const("P", w(3, d, scale=0.7))])])
    h = g.op("Add", [emb, pe])
    for l in range(LAYERS):
        cs = g.op("CumSum", [g.op("Mul", [h, amu]), g.const("ax1s", np.array(1, np.int64))])
        mix = g.op("Mul", [g.op("MatMul", [cs, g.const(f"C{l}", w(d, d))]), g.const("tenth", np.array(0.1, np.float32))])
        h = g.op("Tanh", [g.op("Add", [g.op("MatMul", [h, g.const(f"W{l}", w(d, d))]), mix])])
        if l < len(ds):
            h = scatter(g, h, vis, ds[l], add=True)
    return g.op("Identity", [h], out=out)


def save(path, g, inputs, outputs):
    graph = helper.make_graph(
        g.nodes, "g", inputs, outputs, [numpy_helper.from_array(v, k) for k, v in g.inits.items()]
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], producer_name="pir2-test")
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)


def rope_index(ids, att, image_token, vision_start, grids, merge):
    """Qwen3-VL's multimodal positions (transformers' `get_rope_index`, batch of one)."""
    ids, att = np.asarray(ids), np.asarray(att)
    out = np.ones((3, len(ids)), dtype=np.int64)
    toks = ids[att == 1].tolist()
    n_img = 0
    if vision_start is not None:
        n_img = sum(1 for i in range(len(toks) - 1) if toks[i] == vision_start and toks[i + 1] == image_token)
    chunks, st = [], 0

    def start():
        return int(chunks[-1].max()) + 1 if chunks else 0

    for k in range(n_img):
        ed = toks.index(image_token, st)
        t, h, w_ = grids[k]
        lt, lh, lw = t, h // merge, w_ // merge
        s0 = start()
        chunks.append(np.tile(np.arange(ed - st), (3, 1)) + s0)
        ti = np.repeat(np.arange(lt), lh * lw)
        hi = np.tile(np.repeat(np.arange(lh), lw), lt)
        wi = np.tile(np.arange(lw), lt * lh)
        chunks.append(np.stack([ti, hi, wi]) + (ed - st) + s0)
        st = ed + lt * lh * lw
    if st < len(toks):
        s0 = start()
        chunks.append(np.tile(np.arange(len(toks) - st), (3, 1)) + s0)
    out[:, att == 1] = np.concatenate(chunks, axis=1)
    return out


def write_safetensors(path, tensors):
    """tensors: name -> (dtype str, shape, raw bytes)."""
    header, off = {}, 0
    for name, (dt, shape, raw) in tensors.items():
        header[name] = {"dtype": dt, "shape": list(shape), "data_offsets": [off, off + len(raw)]}
        off += len(raw)
    h = json.dumps(header).encode()
    h += b" " * ((8 - len(h) % 8) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for _, (_, _, raw) in tensors.items():
            f.write(raw)


def to_f32(g, name, ty):
    """An input declared `ty`, as float32 inside the graph."""
    return name if ty == F else g.op("Cast", [name], to=F)


def main(spec_path, out, variant):
    variants = set(filter(None, variant.split(",")))
    spec = json.load(open(spec_path))
    ids, att = spec["ids"], spec["attention"]
    v, s, p, tp, m = spec["views"], spec["side"], spec["patch"], spec["temporal"], spec["merge"]
    d, n, vocab = spec["d"], spec["image_tokens"], spec["vocab"]
    g_side = s // p
    p_rows, patch_dim, t_len = v * g_side * g_side, 3 * tp * p * p, len(ids)
    assert n == v * (g_side // m) ** 2, "image_tokens does not fit the patch grid"

    pos = rope_index(ids, att, spec["image_token"], spec["vision_start"], [(1, g_side, g_side)] * v, m)
    json.dump(pos.tolist(), open(f"{out}/position_ids.json", "w"))

    # Token table, BF16-exact (what the Rust reader widens is what the fused graph holds).
    bits = (w(vocab, d, scale=0.5).view(np.uint32) >> 16).astype(np.uint16)
    table = (bits.astype(np.uint32) << 16).view(np.float32)
    write_safetensors(
        f"{out}/model.safetensors",
        {
            "action_head.vlln.bias": ("F32", [d], np.zeros(d, np.float32).tobytes()),
            spec["key"]: ("BF16", [vocab, d], bits.astype("<u2").tobytes()),
        },
    )

    # The stand-ins are built twice from the same seed position, so their weights agree.
    state = rng.bit_generator.state

    def seeded():
        rng.bit_generator.state = state

    seeded()
    vt = BF16 if "vit_bf16" in variants else F
    g = Builder("vit/")
    img, ds = vit(g, to_f32(g, "pixel_values", vt), p_rows, patch_dim, n, m * m, d)
    g.op("Identity" if vt == F else "Cast", [img], out="image_embeds", **({} if vt == F else {"to": vt}))
    dsf = g.op("Concat", [g.op("Unsqueeze", [x, g.const("ax0", np.array([0], np.int64))]) for x in ds], axis=0)
    g.op("Identity" if vt == F else "Cast", [dsf], out="deepstack_features", **({} if vt == F else {"to": vt}))
    save(
        f"{out}/onnx/vit_{'bf16' if vt == BF16 else 'fp32'}.onnx",
        g,
        [helper.make_tensor_value_info("pixel_values", vt, [p_rows, patch_dim])],
        [
            helper.make_tensor_value_info("image_embeds", vt, [n, d]),
            helper.make_tensor_value_info("deepstack_features", vt, [DEEPSTACK, n, d]),
        ],
    )
    vit_state = rng.bit_generator.state

    d_llm = d - 4 if "wrong_width" in variants else d
    emb_name = "input_embeds" if "wrong_name" in variants else "inputs_embeds"
    bf16_file = bool(variants & {"llm_bf16", "llm_bf16_matmul"})
    lt = BF16 if bf16_file else F16 if "llm_f16" in variants else F  # boundary float type
    et = F64 if "llm_f64" in variants else lt  # inputs_embeds
    g = Builder("llm/")
    emb = to_f32(g, emb_name, et)
    if "llm_bf16_matmul" in variants:
        eye = g.op("Cast", [g.const("eye", np.eye(d_llm, dtype=np.float32))], to=BF16)
        emb = g.op("Cast", [g.op("MatMul", [emb_name, eye])], to=F)
    ds_in = [to_f32(g, f"deepstack_{l}", lt) for l in range(DEEPSTACK)]
    y = llm(g, emb, "attention_mask", "position_ids", "visual_pos_masks", ds_in, d_llm, "embeddings" if lt == F else "embeddings_f32")
    if lt != F:
        g.op("Cast", [y], out="embeddings", to=lt)
    save(
        f"{out}/onnx/llm_{'bf16' if bf16_file else 'fp32'}.onnx",
        g,
        [
            helper.make_tensor_value_info(emb_name, et, [1, "seq_len", d_llm]),
            helper.make_tensor_value_info("attention_mask", I, [1, "seq_len"]),
            helper.make_tensor_value_info("position_ids", I, [3, 1, "seq_len"]),
            helper.make_tensor_value_info("visual_pos_masks", B, [1, "seq_len"]),
        ]
        + [helper.make_tensor_value_info(f"deepstack_{l}", lt, [n, d_llm]) for l in range(DEEPSTACK)],
        [helper.make_tensor_value_info("embeddings", lt, [1, "seq_len", d_llm])],
    )

    # The fused composition: same weights (same seed positions), glue as ONNX ops.
    seeded()
    g = Builder("vit/")
    x = g.op("Unsqueeze", ["pixel_values", g.const("ax1", np.array([1], np.int64))])  # [V,1,3,s,s]
    x = g.op("Concat", [x] * tp, axis=1)  # the image repeated along time
    x = g.op("Reshape", [x, g.const("grid", np.array([v, tp, 3, g_side // m, m, p, g_side // m, m, p], np.int64))])
    x = g.op("Transpose", [x], perm=[0, 3, 6, 4, 7, 2, 1, 5, 8])
    rows = g.op("Reshape", [x, g.const("rows", np.array([p_rows, patch_dim], np.int64))])
    img, ds = vit(g, rows, p_rows, patch_dim, n, m * m, d)
    vit_nodes, vit_inits = g.nodes, g.inits
    assert rng.bit_generator.state == vit_state
    g = Builder("llm/")
    g.nodes, g.inits = vit_nodes, vit_inits
    emb = g.op("Gather", [g.const("embed_tokens", table), "input_ids"], axis=0)
    mask = g.op("Equal", ["input_ids", g.const("image_token", np.array(spec["image_token"], np.int64))])
    emb = scatter(g, emb, mask, img, add=False)
    positions = g.const("position_ids", pos.reshape(3, 1, t_len).astype(np.int64))
    llm(g, emb, "attention_mask", positions, mask, ds, d, "embeddings")
    save(
        f"{out}/fused_backbone.onnx",
        g,
        [
            helper.make_tensor_value_info("pixel_values", F, [v, 3, s, s]),
            helper.make_tensor_value_info("input_ids", I, [1, t_len]),
            helper.make_tensor_value_info("attention_mask", I, [1, t_len]),
        ],
        [helper.make_tensor_value_info("embeddings", F, [1, t_len, d])],
    )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else "")
