"""Goal-reaching envs that no default was chosen on, for checking a custom-env default
beyond the envs it was tuned on (results/README.md, issue 31). Factories for
`--factory check_envs:NAME` with bench/ on PYTHONPATH:

    PYTHONPATH=bench python3 bench/custom_env_results.py target/release/saver --factory check_envs:heavy ...

heavy: the point mass in the plane with a fifth of the drag and half the force
  (terminal speed 2.5; a push of 1 takes ~40 steps to stop the mass from full speed).
pointmass4: the point mass in four coordinates (drag 0.05, force 1).
lagged: a body in the plane whose velocity follows the commanded one with a lag
  (v' = v + 0.2 (2a - v), p' = p + 0.1 v'): the action sets where the velocity goes,
  not the acceleration. The same equations as the point mass with drag 0.2 and force 4
  (the results' rows were made with an own class for it, equal to within 1.3e-15 over
  3,549 steps of random pushes).
"""
from saver_actor.examples import PointMass, _pointmass_decl


def heavy(radius: float = 0.05):
    def make(render_mode=None):
        return PointMass(drag=0.02, accel=0.5, radius=radius, render_mode=render_mode)

    return make, _pointmass_decl("heavy", make())


def pointmass4(radius: float = 0.05):
    def make(render_mode=None):
        return PointMass(radius=radius, render_mode=render_mode, n=4)

    return make, _pointmass_decl("pointmass4", make())


def lagged(radius: float = 0.05):
    """v' = v + 0.2 (2a - v) = 0.8 v + 0.4 a: the point mass with drag 0.2 and force 4
    (terminal speed 2), written as a velocity command followed with a lag."""
    def make(render_mode=None):
        return PointMass(drag=0.2, accel=4.0, radius=radius, render_mode=render_mode)

    return make, _pointmass_decl("lagged", make())
