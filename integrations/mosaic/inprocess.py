"""Mosaic's harness with every solver's Tesseract opened in this process.

The harness runs each solver in a Docker image built from its Tesseract
folder; here there is no Docker and no GPU. Its runner opens a tag
``inprocess:PATH`` as ``Tesseract.from_tesseract_api(PATH)``: this sets that
tag on every discovered solver of every problem, then hands the arguments
to ``mosaic run`` (add ``--no-build --hardware all``; scripts/mosaic does).

    python integrations/mosaic/inprocess.py -p ns-grid -s diffsim,jax-cfd --no-build --hardware all
"""

import sys

from mosaic.benchmarks.cli import app
from mosaic.benchmarks.problems import _registry


def main() -> None:
    for problem in _registry().values():
        for spec in problem.solvers:
            api = problem.tesseract_dir / spec.dir / "tesseract_api.py"
            if api.exists():
                spec.image_tag = f"inprocess:{api}"
    app(["run", *sys.argv[1:]], standalone_mode=True)


if __name__ == "__main__":
    main()
