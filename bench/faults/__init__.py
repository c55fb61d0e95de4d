"""Fault campaign: corrupted links, hostile files and pictures, Ctrl-C, against the drivers and the CLI.

Prints one JSON object. Every fault is classified into exactly one outcome, judged against the truth
the simulators own (their state is read in-process, never from the driver):

- ``clear_error``: the software refused or failed with one of the project's errors (a message, exit
  code 3/4/5, or 130 after Ctrl-C), and the cell is as it should be;
- ``no_effect``: the operation succeeded and what it returned or did is the truth;
- ``hang``: no answer within the bound (the driver's own bound plus a margin; a CLI killed after its
  timeout);
- ``traceback``: an exception outside the project's error tree, a CLI exit 1 or a "Traceback";
- ``unsafe``: a motion other than the one checked (a corrupted motion command executed, a motion run
  twice), a motion reported complete while the arm is elsewhere, a motion still running after the
  software gave up, a speed above the driver's maximum applied, a valve energised after the driver
  gave up, jaws driven the other way;
- ``wrong_value``: a value accepted that differs from the truth (a WHERE pose, a location, a jaw state,
  valve outputs, a calibration or cell file's content, a speed) - including the ones no check can see,
  which are also counted under ``invisible`` with the reason;
- ``lost_file``: a calibration file lost, changed or left half-written.

Sections (each fault kind is named ``section.detail``):

- ``val.<h2d|d2h>.<fault>``: the VAL-II simulator (``selfview.mocks.val_controller``) on TCP behind a
  corrupting proxy (``bench/_proxy.py``, the serial-cable model: the controller never sees the host
  leave), the driver ``selfview.drivers.puma_val_serial`` on ``socket://``, every operation through the
  engine (whose cleanup sends ABORT). ``h2d`` corrupts what the host sends, ``d2h`` what it receives.
- ``modbus.<h2d|d2h>.<fault>``: the valve terminal (``selfview.mocks.valve_terminal``) behind the proxy,
  the gripper driver with its poller, jaw motions through the engine (whose cleanup makes the valve safe).
- ``calfile.<fault>`` / ``cellfile.<fault>``: hostile files through ``selfview.calfile.load_calibration``
  and ``selfview.cell.load_cell`` (in a worker process with a memory limit and a timeout per file).
- ``cli.<calfile|cellfile|picture>.<fault>``: hostile files and pictures through ``selfview track`` and
  ``selfview calibrate --image`` (subprocess with a timeout; exit code, stderr, the calibration file).
- ``sigint.<park|calibrate>``: Ctrl-C at a random moment of ``selfview park`` and of the cell's
  calibrate procedure on the simulated devices (held in this process; the command talks to them with
  ``--real``, through the proxy's serial-cable model, so the controller goes on when the host leaves, as
  a real one does): exit 130, the valve safe, no motion after, the calibration file intact. The
  calibrate procedure runs as a lab script runs it (``CellSession.calibrate``, the CLI's exit codes),
  as ``selfview calibrate`` without ``--image`` is refused by its parser today.

- ``signal.<command>.<SIGNAL>[-twice]``: SIGINT, SIGTERM, SIGHUP or SIGQUIT (once, or twice 0-30 ms apart) during
  ``park``, ``robot ready``, ``robot depart`` and the calibrate procedure: ABORT received if the arm was
  moving, the arm stopped, the valve safe, exit 128 + the signal's number (``signals.py``);
- ``devices.<robot|gripper>``: a second process on the robot's port or the valve terminal during ``park``:
  refused, or unsafe if the simulator executed its command (``devices.py``);
- ``save.<call>``: a calibration save killed just before each of its file-system calls: the file loads,
  and the next save leaves no temporary file (``saves.py``);
- ``files.<argument>.<zero|fifo|sparse|full|readonly>`` and ``fuzz.<argument>``: endless and huge files and
  FIFOs for every file argument (refused within 2 s and 200 MB), /dev/full and a read-only folder for every
  output, numbers and 300-character names at the command line (``paths.py``).

    python -m selfview.bench.faults [--seed 1] [--faults 10000] [--budget-s 480] [--quick]

Timing matters to some faults (a stall against a timeout, the gripper's poller), so two runs with one
seed inject the same faults in the same order but a few outcomes can differ between machines.
"""
