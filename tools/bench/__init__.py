"""``topoexplore bench``: benchmarks that print figures (not timed tests).

    topoexplore bench stages [--sizes 100,300,1000] [--json] [--bus] [--worlds paper-room,office]
    topoexplore bench explore [--worlds ...] [--strategies ...] [--seeds N] [--out DIR] [--bus]
    topoexplore bench inproc [--worlds ...] [--strategies ...] [--seeds N] [--set k=v ...]
    topoexplore bench robust [--half tune|held|real|all] [--strategies ...] [--quick]
    topoexplore bench oracle [--worlds ...] [--corpus DIR] [--from-results SRC ...]
    topoexplore bench posetrace TRACE.npz [--stretch 5] [--worst 8]
    topoexplore bench record [--world office] [--speed 4] [--sim-time 120] [--repeats 2]
    topoexplore bench faults [--world office] [--speed 4] [--faults kill:mapper,stop:planner,router]
    topoexplore bench fuzz [--per-key 10000] [--rate 2000] [--world paper-room]
    topoexplore bench hangs [--tries 20] [--cases disk-full,broken-pipe,signals]
    topoexplore bench codec [--repeats 2000] [--json]

``stages`` (:mod:`.stages`, :mod:`.bus`) times every core and the bus; ``explore``
(:mod:`.explore`) runs the strategy comparison suite, in process with a sample checked on
the real processes, or all on them (``--bus``); ``inproc``
(:mod:`.inproc`) runs the same cores in one process for parameter sweeps; ``oracle``
(:mod:`.oracle`) divides their paths by a short tour planned on the true map; ``posetrace``
(:mod:`.posetrace`) finds where a localized run's pose went wrong; ``record``
(:mod:`.recording`) measures what ``run --record`` costs the services in real time; ``faults``
(:mod:`.faults`) runs explorations while it kills, freezes and restarts processes; ``fuzz``
(:mod:`.fuzz`) floods a running stack with malformed messages on every key it subscribes;
``hangs`` (:mod:`.hangs`) checks that ``run`` comes down, with its children, after a full
disk, a broken pipe or back-to-back signals; ``codec`` (:mod:`.codec`) gives each message's
size and the cost of its conversion and codec.
"""

from __future__ import annotations

import sys

_USAGE = ("usage: topoexplore bench {stages,explore,inproc,robust,oracle,posetrace,record,faults,"
          "fuzz,hangs,codec} [options]  (-h for help)")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in ("stages", "explore", "inproc", "robust", "oracle",
                                   "posetrace", "record", "faults", "fuzz", "hangs", "codec"):
        print(_USAGE, file=sys.stderr)
        return 2
    if argv[0] == "stages":
        from topoexplore.tools.bench import bus

        return bus.stages_main(argv[1:])
    if argv[0] == "codec":
        from topoexplore.tools.bench import codec

        return codec.main(argv[1:])
    if argv[0] == "inproc":
        from topoexplore.tools.bench import inproc

        return inproc.main(argv[1:])
    if argv[0] == "oracle":
        from topoexplore.tools.bench import oracle

        return oracle.main(argv[1:])
    if argv[0] == "posetrace":
        from topoexplore.tools.bench import posetrace

        return posetrace.main(argv[1:])
    if argv[0] == "record":
        from topoexplore.tools.bench import recording

        return recording.main(argv[1:])
    if argv[0] == "fuzz":
        from topoexplore.tools.bench import fuzz

        return fuzz.main(argv[1:])
    if argv[0] == "hangs":
        from topoexplore.tools.bench import hangs

        return hangs.main(argv[1:])
    if argv[0] == "faults":
        from topoexplore.tools.bench import faults

        return faults.main(argv[1:])
    if argv[0] == "robust":
        from topoexplore.tools.bench import robust

        return robust.main(argv[1:])
    from topoexplore.tools.bench import explore

    return explore.main(argv[1:])


if __name__ == "__main__":
    raise SystemExit(main())
