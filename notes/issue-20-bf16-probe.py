"""Which ops does ONNX Runtime's CPU execution provider run in bfloat16 (and float16)?

Issue 20, notes/issue-20-bf16.md. Run: `source .native/env.sh && $PIR2_PYTHON notes/issue-20-bf16-probe.py`.

Each op gets its own graph: f32 inputs -> Cast(to=T) -> op in T -> Cast(to=f32) -> output,
plus a boundary-only graph with T inputs/outputs. A session is created (ORT_ENABLE_ALL and
ORT_DISABLE_ALL) and run; the error, if any, is recorded.
"""
import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto as TP, helper, numpy_helper

F = TP.FLOAT

def case(name, op, n_float_in, shape, attrs=None, extra_inits=(), extra_in_names=(), domain="", out_is_float=True):
    return dict(name=name, op=op, n=n_float_in, shape=shape, attrs=attrs or {}, inits=list(extra_inits), extra=list(extra_in_names), domain=domain, out_float=out_is_float)

def build(c, T):
    nodes, inputs, inits = [], [], []
    op_ins = []
    for i in range(c["n"]):
        inputs.append(helper.make_tensor_value_info(f"x{i}", F, c["shape"]))
        nodes.append(helper.make_node("Cast", [f"x{i}"], [f"c{i}"], to=T))
        op_ins.append(f"c{i}")
    for nm in c["extra"]:
        op_ins.append(nm)
    for arr, nm, cast_to_T in c["inits"]:
        if cast_to_T:
            inits.append(numpy_helper.from_array(arr.astype(np.float32), nm + "_f"))
            nodes.append(helper.make_node("Cast", [nm + "_f"], [nm], to=T))
        else:
            inits.append(numpy_helper.from_array(arr, nm))
    nodes.append(helper.make_node(c["op"], op_ins, ["y"], domain=c["domain"], **c["attrs"]))
    if c["out_float"]:
        nodes.append(helper.make_node("Cast", ["y"], ["out"], to=F))
        out = helper.make_tensor_value_info("out", F, None)
    else:
        nodes.append(helper.make_node("Identity", ["y"], ["out"]))
        out = helper.make_tensor_value_info("out", TP.BOOL, None)
    g = helper.make_graph(nodes, "p", inputs, [out], inits)
    opsets = [helper.make_opsetid("", 19)]
    if c["domain"]:
        opsets.append(helper.make_opsetid(c["domain"], 1))
    m = helper.make_model(g, opset_imports=opsets)
    m.ir_version = 9
    return m

def run(m, level):
    so = ort.SessionOptions()
    so.graph_optimization_level = level
    so.log_severity_level = 3
    try:
        s = ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"])
    except Exception as e:
        msg = str(e).split("\n")[0]
        return "LOAD-FAIL: " + msg[msg.find("Could not find"):][:110] if "Could not find" in msg else "LOAD-FAIL: " + msg[:140]
    feeds = {i.name: np.random.default_rng(0).standard_normal([d if isinstance(d, int) else 2 for d in i.shape]).astype(np.float32) for i in s.get_inputs()}
    try:
        s.run(None, feeds)
        return "ok"
    except Exception as e:
        return "RUN-FAIL: " + str(e).split("\n")[0][:140]

S = [2, 4, 8]
i64 = lambda v: np.array(v, np.int64)
cases = [
    case("Identity", "Identity", 1, S),
    case("Add", "Add", 2, S), case("Sub", "Sub", 2, S), case("Mul", "Mul", 2, S), case("Div", "Div", 2, S),
    case("Neg", "Neg", 1, S), case("Pow", "Pow", 2, S), case("Sqrt", "Sqrt", 1, S), case("Reciprocal", "Reciprocal", 1, S),
    case("MatMul", "MatMul", 1, S, extra_inits=[(np.ones((8, 8)), "w", True)], extra_in_names=["w"]),
    case("Gemm", "Gemm", 1, [4, 8], extra_inits=[(np.ones((8, 8)), "w", True)], extra_in_names=["w"]),
    case("Sigmoid", "Sigmoid", 1, S), case("Tanh", "Tanh", 1, S), case("Softmax", "Softmax", 1, S, attrs=dict(axis=-1)),
    case("Cos", "Cos", 1, S), case("Sin", "Sin", 1, S), case("Erf", "Erf", 1, S),
    case("ReduceMean", "ReduceMean", 1, S, extra_inits=[(i64([-1]), "ax", False)], extra_in_names=["ax"]),
    case("LayerNormalization", "LayerNormalization", 1, S, extra_inits=[(np.ones(8), "g", True), (np.zeros(8), "b", True)], extra_in_names=["g", "b"], attrs=dict(axis=-1)),
    case("SimplifiedLayerNormalization", "SimplifiedLayerNormalization", 1, S, extra_inits=[(np.ones(8), "g", True)], extra_in_names=["g"], attrs=dict(axis=-1)),
    case("Concat", "Concat", 2, S, attrs=dict(axis=-1)),
    case("Slice", "Slice", 1, S, extra_inits=[(i64([0]), "st", False), (i64([4]), "en", False), (i64([-1]), "ax", False)], extra_in_names=["st", "en", "ax"]),
    case("Reshape", "Reshape", 1, S, extra_inits=[(i64([2, 32]), "sh", False)], extra_in_names=["sh"]),
    case("Transpose", "Transpose", 1, S, attrs=dict(perm=[0, 2, 1])),
    case("Unsqueeze", "Unsqueeze", 1, S, extra_inits=[(i64([0]), "ax", False)], extra_in_names=["ax"]),
    case("Expand", "Expand", 1, [1, 4, 8], extra_inits=[(i64([3, 4, 8]), "sh", False)], extra_in_names=["sh"]),
    case("Gather", "Gather", 1, S, extra_inits=[(i64([0, 1]), "ix", False)], extra_in_names=["ix"], attrs=dict(axis=1)),
    case("Where", "Where", 2, S),  # built by build_where (needs a bool condition)
    case("Trilu", "Trilu", 1, [4, 4], attrs=dict(upper=1)),
    case("ScatterND", "ScatterND", 1, [4, 8], extra_inits=[(i64([[1]]), "ix", False), (np.ones((1, 8)), "up", True)], extra_in_names=["ix", "up"]),
    case("Equal", "Equal", 2, S, out_is_float=False),
    case("CumSum", "CumSum", 1, S, extra_inits=[(i64(1), "ax", False)], extra_in_names=["ax"]),
    case("Max", "Max", 2, S),
    case("ReduceSum", "ReduceSum", 1, S, extra_inits=[(i64([-1]), "ax", False)], extra_in_names=["ax"]),
]
# Where(cond, a, b): cond first.
def build_where(T):
    nodes = [helper.make_node("Cast", ["x0"], ["c0"], to=T), helper.make_node("Cast", ["x1"], ["c1"], to=T),
             helper.make_node("Greater", ["x0", "x1"], ["cond"]),
             helper.make_node("Where", ["cond", "c0", "c1"], ["y"]), helper.make_node("Cast", ["y"], ["out"], to=F)]
    g = helper.make_graph(nodes, "p", [helper.make_tensor_value_info(f"x{i}", F, S) for i in range(2)], [helper.make_tensor_value_info("out", F, None)])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 19)]); m.ir_version = 9
    return m
def boundary(T):
    nodes = [helper.make_node("Cast", ["x"], ["xf"], to=F), helper.make_node("Tanh", ["xf"], ["yf"]), helper.make_node("Cast", ["yf"], ["y"], to=T)]
    g = helper.make_graph(nodes, "p", [helper.make_tensor_value_info("x", T, S)], [helper.make_tensor_value_info("y", T, S)])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 19)]); m.ir_version = 9
    return m

print("onnxruntime", ort.__version__, ort.get_device(), ort.get_available_providers())
L = [("all", ort.GraphOptimizationLevel.ORT_ENABLE_ALL), ("none", ort.GraphOptimizationLevel.ORT_DISABLE_ALL)]
for tname, T in [("bf16", TP.BFLOAT16), ("f16", TP.FLOAT16)]:
    print(f"== {tname}")
    for c in cases:
        m = build_where(T) if c["name"] == "Where" else build(c, T)
        r = {ln: run(m, lv) for ln, lv in L}
        print(f"{c['name']:30s} all: {r['all']:60s} none: {r['none']}")
    so = ort.SessionOptions(); so.log_severity_level = 3
    try:
        s = ort.InferenceSession(boundary(T).SerializeToString(), so, providers=["CPUExecutionProvider"])
        print("boundary-only (Cast in/out, f32 interior): load ok;", [(i.name, i.type) for i in s.get_inputs()], [(o.name, o.type) for o in s.get_outputs()])
    except Exception as e:
        print("boundary-only: LOAD-FAIL", str(e)[:200])
