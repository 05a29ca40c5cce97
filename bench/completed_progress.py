"""The example envs with the progress reward completed at success
(`EnvDecl(complete_at_success=True)`; results/README.md, "The horizon and the control
cost", issue 31), for `--factory`. Actors import it from bench/:

    PYTHONPATH=bench python3 bench/custom_env_results.py target/release/saver \\
        --factory completed_progress:pointmass --steps 300000 --seeds 0 --algos "saver --gamma 0.97"
"""
import dataclasses

from saver_actor import examples


def pointmass():
    make_env, decl = examples.pointmass()
    return make_env, dataclasses.replace(decl, complete_at_success=True)


def reacher():
    make_env, decl = examples.reacher()
    return make_env, dataclasses.replace(decl, complete_at_success=True)
