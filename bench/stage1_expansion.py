"""TwinRL's motivating experiment and Table I, reproduced in the plant.

Thin runner around :func:`twinrl_learn.studies.table1.run_stage1` (also ``twinrl bench stage1``).
Usage::

    python bench/stage1_expansion.py --out out/stage1 --policies state
    python bench/stage1_expansion.py --out out/stage1_vla --policies vla --tasks pick_place
"""

from twinrl_learn.cli import bench_stage1

if __name__ == "__main__":
    import typer

    typer.run(bench_stage1)
