#!/usr/bin/env python3
"""Checks an ONNX policy written by `rall export` with Python onnxruntime (a runtime
rall did not write): the reference observations of the JSON sidecar must give the
sidecar's actions within its tolerance, as one batch and row by row.

usage: python3 tests/check_onnx.py OUT.onnx [OUT.json]
"""
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort


def main() -> int:
    if len(sys.argv) not in (2, 3):
        print(__doc__, file=sys.stderr)
        return 2
    onnx_path = Path(sys.argv[1])
    side_path = Path(sys.argv[2]) if len(sys.argv) == 3 else onnx_path.with_suffix(".json")
    side = json.loads(side_path.read_text())
    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    inputs = sess.get_inputs()
    outputs = sess.get_outputs()
    assert [i.name for i in inputs] == [i["name"] for i in side["onnx"]["inputs"]], inputs
    assert inputs[0].shape[0] == "batch", f"batch dimension is not dynamic: {inputs[0].shape}"
    assert outputs[0].name == "actions", outputs
    obs = np.asarray(side["reference"]["observations"], dtype=np.float32)
    want = np.asarray(side["reference"]["actions"], dtype=np.float32)
    tol = float(side["reference"]["tolerance_abs"])
    assert obs.shape[1] == side["observation"]["dim"], obs.shape
    feeds = {"obs": obs}
    if "history" in side["reference"]:  # an RMA student: obs and its history
        feeds["history"] = np.asarray(side["reference"]["history"], dtype=np.float32)
        assert feeds["history"].shape[1] == side["history"]["width"], feeds["history"].shape
    got = sess.run(["actions"], feeds)[0]
    err = float(np.max(np.abs(got - want)))
    rows = max(float(np.max(np.abs(
        sess.run(["actions"], {k: v[i][None] for k, v in feeds.items()})[0][0] - want[i])))
        for i in range(len(obs)))
    print(f"onnxruntime {ort.__version__}: {onnx_path} on {len(obs)} reference observations: "
          f"max |diff| {err:.2e} (batch), {rows:.2e} (batch 1), tolerance {tol:.0e}")
    if not (err <= tol and rows <= tol):
        print("FAIL: onnxruntime disagrees with rall", file=sys.stderr)
        return 1
    if float(np.max(np.abs(want))) < 1e-3:
        print("FAIL: the reference actions are all ~0, nothing is checked", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
