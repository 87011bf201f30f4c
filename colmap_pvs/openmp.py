"""How OpenMP's threads wait, in the processes colmap-pvs starts (the command line, Ray's workers).

torch runs its parallel loops on OpenMP threads (GNU OpenMP in its Linux wheels). A thread that is done
waits for the others. Busy-waiting, OpenMP's default, holds on to a core, so on a machine doing other
work the threads wait for each other's cores and a run becomes several times slower. Sleeping at once
(``OMP_WAIT_POLICY=PASSIVE``) makes the many short parallel loops of a forward pass slower on a quiet
machine. GNU OpenMP's ``GOMP_SPINCOUNT`` spins a little, then sleeps: close to the faster of the two in
either case (benchmarks/RESULTS.md). Other OpenMP runtimes read the policy alone.

Both must be set before torch is imported; the library itself never sets them in its own process (it
passes :func:`wait_env` to the Ray workers it starts).
"""

from __future__ import annotations

from collections.abc import Mapping, MutableMapping

#: The environment of a process that runs torch for colmap-pvs.
WAIT_ENV = {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "1000"}


def wait_env(environ: Mapping[str, str]) -> dict[str, str]:
    """How OpenMP should wait, given ``environ``: the user's own setting of either variable where it has
    one, else :data:`WAIT_ENV`."""
    own = {key: environ[key] for key in WAIT_ENV if key in environ}
    return own or dict(WAIT_ENV)


def set_wait_env(environ: MutableMapping[str, str]) -> None:
    """Set :data:`WAIT_ENV` in ``environ`` unless it already says how OpenMP waits (either variable)."""
    environ.update(wait_env(environ))
