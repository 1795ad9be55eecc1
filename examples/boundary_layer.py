"""The paper's boundary-layer experiment on synthetic data, end to end.

    python examples/boundary_layer.py [small|paper] [OUT_DIR]

Same as ``plenocl demo boundary-layer --size SIZE --out OUT_DIR``: simulates the image
pair and a white image, calibrates, reconstructs, correlates and compares with the
truth; writes summary.json, field.vti and figures into OUT_DIR (resumable).
"""

from __future__ import annotations

import json
import sys

from plenocl.demo.boundary_layer import run_boundary_layer


def main(size: str = "small", out_dir: str = "boundary_layer_demo") -> None:
    """Run the example and print its summary."""
    summary = run_boundary_layer(size, out_dir)
    summary.pop("profile")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main(*sys.argv[1:3])
