"""Fault campaign: corrupted links, hostile files and pictures, signals, host stalls, standard output closed early.

Against the drivers and the CLI.

Prints one JSON object: every fault (kind ``section.detail``) classified into exactly one outcome
(``common.OUTCOMES``), judged against the truth the simulators own, never from the driver. Each
section's module says what it injects.

    python -m selfview.bench.faults [--seed 1] [--faults 10000] [--budget-s 600] [--quick]

Two runs with one seed inject the same faults in the same order, but timing matters to some (a stall
against a timeout, the gripper's poller), so a few outcomes can differ between machines.
"""
