"""Writes the bfloat16 test graph of gr00t_onnx_f32.rs with the `onnx` package.

argv: values.bin (little-endian f32: W [64, 32], then b [32]), out.onnx, mode ("inline" or
"external"). The values are already bfloat16-exact, so truncating them to their upper 16
bits is lossless.

Graph: y = Cast<float>(Tanh(Cast<bf16>(MatMul(x, W) + b) * half)), x bfloat16 [2, 64],
W, b bfloat16 initializers, `half` a bfloat16 Constant node (0.5), one Cast to bfloat16 in
the middle and value_info declaring the intermediates bfloat16.
"""

import sys

import numpy as np
import onnx
from onnx import TensorProto, helper

values, out, mode = sys.argv[1], sys.argv[2], sys.argv[3]
f = np.fromfile(values, dtype="<f4")
w, b = f[: 64 * 32], f[64 * 32 :]


def bf16(name, dims, vals):
    bits = (vals.astype("<f4").view("<u4") >> 16).astype("<u2")
    return helper.make_tensor(name, TensorProto.BFLOAT16, dims, bits.tobytes(), raw=True)


nodes = [
    helper.make_node("MatMul", ["x", "W"], ["xw"]),
    helper.make_node("Add", ["xw", "b"], ["z"]),
    helper.make_node("Cast", ["z"], ["zc"], to=TensorProto.BFLOAT16),
    helper.make_node(
        "Constant", [], ["half"], value=bf16("half_value", [], np.array([0.5], "<f4"))
    ),
    helper.make_node("Mul", ["zc", "half"], ["zh"]),
    helper.make_node("Tanh", ["zh"], ["t"]),
    helper.make_node("Cast", ["t"], ["y"], to=TensorProto.FLOAT),
]
graph = helper.make_graph(
    nodes,
    "bf16_test",
    [helper.make_tensor_value_info("x", TensorProto.BFLOAT16, [2, 64])],
    [helper.make_tensor_value_info("y", TensorProto.FLOAT, [2, 32])],
    initializer=[bf16("W", [64, 32], w), bf16("b", [32], b)],
    value_info=[
        helper.make_tensor_value_info(n, TensorProto.BFLOAT16, [2, 32])
        for n in ["xw", "z", "zc", "zh", "t"]
    ],
)
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
model.ir_version = 8
onnx.checker.check_model(model)
if mode == "external":
    onnx.save_model(
        model,
        out,
        save_as_external_data=True,
        all_tensors_to_one_file=True,
        location=out.split("/")[-1] + ".weights",
        size_threshold=0,
    )
else:
    onnx.save_model(model, out)
