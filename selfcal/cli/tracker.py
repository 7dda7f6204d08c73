"""``selfcal simulate|smooth tracker``: laser tracker + inclinometer + beam camera + IMU (patent 004)."""
from __future__ import annotations

from selfcal.cli.common import Verb, output, positive_float


def simulate_arguments(p) -> None:
    p.add_argument("--out", required=True, help="recording folder to write")
    p.add_argument("--duration", type=positive_float, default=600.0, help="run length, s")
    p.add_argument("--faults", action="store_true", help="inject the default fault schedule (truth/ logs it)")
    p.add_argument("--advance-mm-s", type=float, default=1.0, help="advance speed, mm/s")
    p.add_argument("--bursts-per-min", type=float, default=2.0, help="mean vibration bursts per minute")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (motion, bursts, biases, faults)")
    p.add_argument("--noise-seed", type=int, default=1, help="white-noise seed")
    p.add_argument("--overwrite", action="store_true")


def simulate(args) -> None:
    from selfcal.sim.tracker import TrackerScenario
    sc = TrackerScenario(duration_s=args.duration, seed=args.seed, faults=args.faults,
                         advance_mm_s=args.advance_mm_s, burst_rate_per_min=args.bursts_per_min)
    sc.write(args.out, seed=args.noise_seed, overwrite=args.overwrite)
    print(f"wrote {args.out}: {args.duration:.0f} s, {len(sc.bursts)} vibration bursts, {len(sc.faults)} injected "
          f"faults (truth/truth.yaml, truth/poses.tum)")


def smooth_arguments(p) -> None:
    p.add_argument("recording")
    p.add_argument("--mode", choices=["batch", "isam2", "fixed-lag"], default="batch",
                   help="batch: LM over all keyframes after the online gating pass; isam2 / fixed-lag: online poses")
    p.add_argument("--no-gating", action="store_true", help="no chi-square gate, no soft-fault detector")
    p.add_argument("--out", required=True, help="TUM trajectory file (t x y z qx qy qz qw) of the IMU body frame")
    p.add_argument("--log", help="JSON lines: every gating decision with its statistic and threshold")


def smooth(args) -> None:
    from selfcal.core.progress import TerminalProgress
    from selfcal.io.atomic import atomic_write_text
    from selfcal.io.recording import read_recording
    from selfcal.pipelines.tracker import smooth_tracker
    with TerminalProgress("smooth tracker") as progress:
        progress("read the recording")
        result = smooth_tracker(read_recording(args.recording), mode=args.mode, gating=not args.no_gating,
                                progress=progress)
    c = result.counts
    print(f"{len(result.t_ns)} poses in {result.seconds:.1f} s ({args.mode}); measurements accepted {c['accepted']}, "
          f"rejected {c['rejected']}, held out {c['held_out']}, removed after a soft-fault alarm {c['removed']} "
          f"(provisional factors replaced: {c['replaced']})")
    atomic_write_text(output(args.out), result.tum_text())
    print(f"trajectory: {args.out}")
    if args.log:
        atomic_write_text(output(args.log), result.decisions_jsonl())
        print(f"decisions: {args.log}")


VERBS = (
    Verb("simulate", "TBM laser-tracker target with vibration bursts and faults (patent 004)", simulate_arguments,
         simulate),
    Verb("smooth", "laser tracker + inclinometer + beam camera + IMU, fault-gated (patent 004)", smooth_arguments,
         smooth),
)
