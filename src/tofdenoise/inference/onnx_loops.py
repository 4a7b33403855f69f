"""One rewrite of an exported ONNX graph: per-step outputs of a ``Loop`` collected as a sequence become scan outputs.

A ``torch.jit.script`` loop that appends one tensor per step to a list and stacks the list after the loop (the
export scan's second loop, :mod:`tofdenoise.models.scan.export`) is exported by the TorchScript-based exporter as

    seq0 = SequenceEmpty();  ..., seq = Loop(M, cond, ..., seq0)   (body: seq_out = SequenceInsert(seq_in, value))
    stacked = ConcatFromSequence(seq, axis=0, new_axis=1)

which onnxruntime runs as one sequence insert per step. :func:`sequences_to_scan_outputs` rewrites each such
pattern into the ``Loop``'s own scan output (ONNX stacks the per-step values of a body output that is not carried
along axis 0, which is what ``ConcatFromSequence(axis=0, new_axis=1)`` computes), and leaves every other use of a
sequence alone. Measured gain: docs/benchmarks.md, "ONNX export".
"""

from __future__ import annotations

import onnx
from onnx import helper

__all__ = ["sequences_to_scan_outputs"]


def _attributes(node: onnx.NodeProto) -> dict:
    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def _body(loop: onnx.NodeProto) -> onnx.GraphProto:
    return next(a.g for a in loop.attribute if a.name == "body")


def sequences_to_scan_outputs(graph: onnx.GraphProto) -> int:
    """Rewrite ``graph`` in place (and the graphs nested in its nodes); returns the number of sequences rewritten."""
    count = 0
    for node in graph.node:
        for attr in node.attribute:
            if attr.type == onnx.AttributeProto.GRAPH:
                count += sequences_to_scan_outputs(attr.g)
    producers = {out: node for node in graph.node for out in node.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)
    for name in graph.output:
        consumers.setdefault(name.name, []).append(None)  # a graph output: never rewritten
    for loop in [n for n in graph.node if n.op_type == "Loop"]:
        carried = len(loop.input) - 2  # Loop inputs: trip count, condition, carried values
        for j in reversed(range(carried)):
            if _rewrite_one(graph, loop, j, producers, consumers):
                count += 1
    return count


def _rewrite_one(graph, loop, j: int, producers, consumers) -> bool:
    """Rewrite carried value ``j`` of ``loop`` when it is an empty sequence filled by one insert per step and only
    stacked after the loop; False (graph untouched) otherwise."""
    body = _body(loop)
    start = producers.get(loop.input[2 + j])
    if start is None or start.op_type != "SequenceEmpty" or len(consumers.get(start.output[0], [])) != 1:
        return False
    seq_in, seq_out = body.input[2 + j].name, body.output[1 + j].name
    inserts = [n for n in body.node if n.op_type == "SequenceInsert" and n.output[0] == seq_out]
    if len(inserts) != 1 or list(inserts[0].input) != [seq_in, inserts[0].input[1]]:
        return False  # an insert at a position, or a sequence built some other way
    if any(seq_in in n.input for n in body.node if n is not inserts[0]):
        return False  # the body reads the sequence: it must stay a sequence
    if sum(o.name == seq_out for o in body.output) != 1 or any(seq_out in n.input for n in body.node):
        return False
    users = consumers.get(loop.output[j], [])
    if len(users) != 1 or users[0] is None or users[0].op_type != "ConcatFromSequence":
        return False
    stack = users[0]
    attrs = _attributes(stack)
    if attrs.get("axis") != 0 or attrs.get("new_axis", 0) != 1:
        return False
    value = inserts[0].input[1]
    body.node.remove(inserts[0])
    del body.input[2 + j]
    del body.output[1 + j]
    body.output.append(helper.make_empty_tensor_value_info(value))  # type inferred by the runtime
    outputs = list(loop.output)
    del loop.input[2 + j]
    del loop.output[:]
    loop.output.extend(outputs[:j] + outputs[j + 1 :] + [outputs[j]])  # carried values first, scan outputs last
    stack.op_type = "Identity"
    del stack.attribute[:]
    graph.node.remove(start)
    return True
