"""Mutation check: can the test suite fail? Each mutation is a deliberate bug put into a temporary copy of
the repository; the tests that should catch it run there; it is caught when they fail.

Prints one JSON object: ``caught``, ``total``, ``errors`` (mutations that no longer apply or timed out),
and ``mutations``: a list of {name, file, caught, failed_tests, error, seconds}.

    python bench/mutations.py [--only NAME ...] [--list] [--timeout 600]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Mutation:
    """One deliberate bug: in ``file`` (relative to the repository), ``original`` becomes ``replacement``;
    ``tests`` (pytest node ids or files, relative to the repository) should then fail. ``original``
    must occur in that file exactly once."""

    name: str
    file: str
    original: str
    replacement: str
    tests: tuple[str, ...]
    why: str = ""


MUTATIONS: tuple[Mutation, ...] = (
    # --- the seven that survived the first mutation check --------------------------------------------------
    Mutation(
        "val-echo-first-word",
        "drivers/puma_val_serial/driver.py",
        "            if echo != body:  # the whole line, byte for byte: 'SPEED 02' is not 'SPEED 20'\n",
        '            if echo.split(b" ")[:1] != body.split(b" ")[:1]:\n',
        ("tests/drivers/test_puma_transcript.py::test_an_echo_that_differs_after_its_first_word_is_erased_before_it_runs",
         "tests/drivers/test_puma_transcript.py::test_a_corrupted_motion_command_never_runs"),
        "the VAL echo compared on its first word only: 'SPEED 02' passes for 'SPEED 20' and runs",
    ),
    Mutation(
        "calfile-written-in-place",
        "selfview/files/io_safe.py",
        '    tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"  # see remove_leftovers\n    try:\n'
        "        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 if old_mode is None else old_mode)\n",
        "    tmp = path\n    try:\n"
        "        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666 if old_mode is None else old_mode)\n",
        ("tests/selfview/test_calfile_atomic.py", "tests/selfview/test_calfile.py::test_a_write_that_fails_half_way_leaves_the_old_file",
         "tests/selfview/test_calfile.py::test_a_crash_in_the_middle_of_a_write_leaves_the_old_file"),
        "the calibration writer writes the file in place (a failure midway leaves a torn file)",
    ),
    Mutation(
        "calfile-written-before-read-back",
        "selfview/files/calfile.py",
        "    # check what we are about to write reads back, before it replaces anything\n",
        '    atomic_write(p, text.encode("utf-8"), error=CalibrationFileError, what="calibration file")\n',
        ("tests/selfview/test_calfile.py::test_a_calibration_that_does_not_read_back_is_never_written",
         "tests/selfview/test_calfile_atomic.py"),
        "the file replaced before the check that it reads back",
    ),
    Mutation(
        "recalibration-alarm-limit-unchecked",
        "selfview/estimation/policy.py",
        '        if self.classify(delta_R, d_R) == "alarm":\n',
        "        if False:\n",
        ("tests/selfview/test_policy.py::test_a_recalibration_beyond_the_alarm_limit_raises_the_alarm",),
        "a recalibration that itself measures more than the alarm limit is applied",
    ),
    Mutation(
        "abort-failure-escapes-cleanup",
        "procedures/engine.py",
        "        except Exception as exc:  # never let cleanup itself die: the valve and the closes still follow\n",
        "        except CellError as exc:\n",
        ("tests/procedures/test_engine.py::test_an_abort_that_fails_in_the_cleanup_still_leaves_the_valve_safe_and_closes",),
        "an ABORT that fails with anything but a CellError escapes the engine's cleanup (valve not made safe)",
    ),
    Mutation(
        "v4l2-std-range-unchecked",
        "drivers/frame_grabber_v4l2/url.py",
        "    if not 0 < v < 1 << 64:\n",
        "    if False:\n",
        ("tests/drivers/test_grabber_v4l2.py::test_std_numbers_outside_a_v4l2_std_id_are_refused",),
        "std=0 or a number beyond 64 bits accepted as a video standard",
    ),
    Mutation(
        "min-discs-60",
        "selfview/measurement/discs.py",
        "min_discs: int = 12) -> DiscDetections:",
        "min_discs: int = 60) -> DiscDetections:",
        ("tests/selfview/test_discs.py::test_the_minimum_disc_count", "tests/selfview/test_offline.py::test_robustness"),
        "the minimum disc count raised from 12 to 60: the standard pictures are refused",
    ),
    Mutation(
        "disc-merged-with-a-shadow-not-split",
        "selfview/measurement/discs.py",
        "    if t < 1.5 * DARK_FRACTION:\n",
        "    if True:\n",
        ("tests/selfview/test_discs_photos_boofcv.py::test_a_hands_shadow_over_the_grid_keeps_every_disc_where_opencv_puts_it",),
        "a disc merged with a shadow's edge by the contrast threshold dropped as 'not elliptical' again",
    ),
    Mutation(
        "disc-centre-weight-without-the-ink-ramp",
        "selfview/measurement/discs.py",
        "    wgt -= start / (full - start)\n",
        "    wgt = c.copy()\n",
        ("tests/selfview/test_discs_photos_boofcv.py::test_a_hands_shadow_over_the_grid_keeps_every_disc_where_opencv_puts_it",),
        "the disc centre weighted by the raw contrast 1 - I / I_paper again, not the share of the disc's ink",
    ),
    Mutation(
        "shadow-edge-level-not-fitted-past-a-mark",
        "selfview/measurement/discs.py",
        "level = again and _edge_level(A[1], A[2], z, np.arctan2(coef[2], coef[1]), tol, marks=True)",
        "level = again and _edge_level(A[1], A[2], z, np.arctan2(coef[2], coef[1]), tol, marks=False)",
        ("tests/selfview/test_shadows.py::test_a_shadow_across_a_real_photograph_keeps_its_discs",),
        "a disc on a shadow's edge beside a printed mark dropped as 'occluded'",
    ),
    Mutation(
        "faint-discs-measured-with-the-glare-left-on",
        "selfview/measurement/discs.py",
        "    if contrast < FAINT:",
        "    if False:",
        ("tests/selfview/test_shadows.py::test_glare_over_a_real_photograph_keeps_its_discs",),
        "a picture under glare or haze (a grey pedestal) measured as it is: its faint discs under the threshold",
    ),
    Mutation(
        "ring-tolerance-blind-to-pixel-noise",
        "selfview/measurement/discs.py",
        "    floor = NOISE_SIGMAS * noise / coef[0] if coef[0] > 0 else 0.0",
        "    floor = 0.0",
        ("tests/selfview/test_discs_photos_boofcv.py::test_sensor_noise_over_a_real_photograph_keeps_its_discs",),
        "a noisy picture's rings judged by the fixed tolerance: discs on paper noisier than it dropped as 'occluded'",
    ),
    Mutation(
        "outlines-smoothed-the-same-in-a-noisy-picture",
        "selfview/measurement/discs.py",
        "    blur = max(OUTLINE_BLUR_PX, rel / (2 * math.sqrt(math.pi) * OUTLINE_NOISE))",
        "    blur = OUTLINE_BLUR_PX",
        ("tests/selfview/test_discs_photos_boofcv.py::test_sensor_noise_over_a_real_photograph_keeps_its_discs",),
        "noise specks in a shadow joined to a disc's blob or cutting its ring: the disc left out",
    ),
    Mutation(
        "paper-level-smoothed-across-the-sheets-edge",
        "selfview/measurement/discs.py",
        "    closed = cv2.max(closed, cv2.blur(closed, (k // 3 | 1, k // 3 | 1)))",
        "    closed = cv2.blur(closed, (k // 3 | 1, k // 3 | 1))",
        ("tests/selfview/test_discs_photos_boofcv.py::test_a_defocused_frame_keeps_the_discs_by_the_sheets_edge",),
        "the paper's level taken darker by the sheet's edge: a blurred picture's outer discs under the threshold",
    ),
    Mutation(
        "left-out-corner-reason-overwritten",
        "selfview/measurement/fingers.py",
        "    fitted.left_out.update({**missed, **result.left_out})\n",
        "    fitted.left_out.update({**result.left_out, **missed})\n",
        ("tests/selfview/test_boards_under_gripper.py::test_offline_calibration_over_a_chessboard_under_the_gripper",),
        "a corner left out off the fingers' shape named as one the search did not find there",
    ),
    Mutation(
        "12-bit-pixels-taken-as-16-bit",
        "selfview/files/io_safe.py",
        "    return 255.0 / ((1 << next(b for b in (8, 10, 12, 14, 16) if int(a.max()) < 1 << b)) - 1)\n",
        "    return 255.0 / 65535\n",
        ("tests/selfview/test_io_safe.py::test_a_16_bit_picture_reads_as_its_cameras_8_bits",
         "tests/selfview/test_discs.py::test_colour_and_16_bit_pictures_are_accepted"),
        "a 10- or 12-bit camera's unshifted pixels read as 16 bits: its pictures 1/16 as bright, or refused as blank",
    ),
    Mutation(
        "grasp-window-on-blank-paper-fails-the-grasp",
        "procedures/grasp.py",
        "            except (CalibrationError, ImageError):\n",
        "            except CalibrationError:\n",
        ("tests/procedures/test_grasp.py::test_a_window_on_a_blank_part_of_the_picture_falls_back_to_the_whole_picture",),
        "a windowed target search on a blank part of the picture ends the grasp instead of searching the whole",
    ),
    Mutation(
        "defocused-discs-not-measured-again",
        "selfview/measurement/discs.py",
        "        for pedestal in (ink, DEFOCUS_PEDESTAL * paper):  # the one that finds most discs, until one finds all\n",
        "        for pedestal in (ink,):\n",
        ("tests/selfview/test_discs_photos_boofcv.py::test_a_badly_defocused_frame_is_measured_with_its_spread_ink",
         "tests/selfview/test_discs_photos_boofcv.py::test_an_over_exposed_frame_keeps_its_discs"),
        "a badly defocused or over-exposed frame's faint discs, under the darkness threshold, left unfound",
    ),
    Mutation(
        "faint-pictures-paper-taken-with-the-bench",
        "selfview/measurement/discs.py",
        "        lit = level >= 0.5 * float(level.max())  # the plate's paper, not a dark bench beside it\n",
        "        lit = level >= 0.0\n",
        ("tests/selfview/test_discs_photos_boofcv.py::test_a_badly_defocused_frame_is_measured_with_its_spread_ink",),
        "a faint picture's paper level and darkest ink taken over the dark bench beside the sheet: no pedestal fits",
    ),
    Mutation(
        "integer-pixels-on-another-scale-read-as-grey-levels",
        "selfview/measurement/discs.py",
        "                                     and not 0 <= a.min() <= a.max() <= 255):",
        "                                     and False):",
        ("tests/selfview/test_discs.py::test_integer_pixels_on_another_scale_are_refused_by_name",),
        "a 12-bit picture handed over as int32 read as 0..255 grey levels: a board or target detector sees it clipped",
    ),
    Mutation(
        "grabber-lock-kept-until-the-source-is-collected",
        "drivers/frame_grabber_v4l2/grabber.py",
        "                if claim is not None:\n                    claim.release()\n",
        "                pass\n",
        ("tests/drivers/test_grabber_v4l2.py::test_the_devices_lock_is_released_on_close_and_on_a_failed_open_whoever_holds_the_source",),
        "the grabber's device lock released only when the source object is collected (a traceback keeps it)",
    ),
    # --- the independence of the test renderer and the off-line pipeline's steps ----------------------------
    Mutation(
        "camera-half-pixel-shift",
        "selfview/maths/camera.py",
        "        u = XY_hat[:, 0] / self.aspect + self.cx\n",
        "        u = XY_hat[:, 0] / self.aspect + self.cx + 0.5\n",
        ("tests/selfview/test_discs.py::test_alt_renderer_truth_is_self_consistent",
         "tests/selfview/test_fingertips.py::test_prediction_agrees_with_the_independent_renderer"),
        "the project's projection half a pixel off its convention (its own renderer follows it along)",
    ),
    Mutation(
        "disc-bias-correction-removed",
        "selfview/estimation/offline.py",
        "    uv_c = correct_plate_bias(det, ts.camera.with_(skew=nominal.skew), ts.C_H_W, cell.plate)\n",
        "    uv_c = det.uv\n",
        ("tests/selfview/test_offline.py::test_accuracy_on_an_independent_renderer",
         "tests/selfview/test_offline.py::test_accuracy_over_30_seeds_on_the_project_renderer"),
        "the off-line calibration without its disc-bias correction",
    ),
    # --- one per safety rule: the robot ------------------------------------------------------------------
    Mutation(
        "abort-after-resync",
        "drivers/puma_val_serial/driver.py",
        '        """A motion\'s wait failed: ABORT first, unconditionally, then confirm (the command lock held)."""\n',
        '        """A motion\'s wait failed."""\n        self._resync()\n',
        ("tests/drivers/test_puma_transcript.py::test_a_motion_that_outlasts_its_wait_is_aborted_first_thing",
         "tests/drivers/test_puma_transcript.py::test_an_abort_that_gets_no_answer_says_so"),
        "after a motion's wait fails, the driver resynchronises (CR, wait for a prompt) before writing ABORT",
    ),
    Mutation(
        "abort-unconfirmed-reported-as-stop",
        "procedures/engine.py",
        '        return str(res), bool(getattr(res, "confirmed", False))\n',
        "        return str(res), True\n",
        ("tests/procedures/test_engine.py::test_an_abort_that_fails_in_the_cleanup_still_leaves_the_valve_safe_and_closes",),
        "the engine reports an unconfirmed ABORT as a stopped robot",
    ),
    Mutation(
        "where-crosscheck-removed",
        "drivers/puma_val_serial/driver.py",
        "            if fit.consistent:\n",
        "            if True:\n",
        ("tests/drivers/test_puma_transcript.py::test_a_digit_swap_in_where_is_read_again",
         "tests/drivers/test_puma_transcript.py::test_a_wrong_oat_convention_is_named_on_the_first_where"),
        "a WHERE whose pose disagrees with the kinematics of its own joints is accepted (digit swaps pass)",
    ),
    Mutation(
        "location-not-reread",
        "drivers/puma_val_serial/driver.py",
        "            return name, self.dialect.pose_to_H(self._location_locked(name))\n",
        '            cached = self.__dict__.setdefault("_stale", {})\n'
        "            if name.upper() not in cached:\n"
        "                cached[name.upper()] = self.dialect.pose_to_H(self._location_locked(name))\n"
        "            return name, cached[name.upper()]\n",
        ("tests/drivers/test_puma_transcript.py::test_a_relocated_target_outside_the_box_is_refused",),
        "a named location's limit check uses a cached copy (a re-taught location passes unchecked)",
    ),
    Mutation(
        "motion-ends-at-a-noise-prompt",
        "drivers/puma_val_serial/driver.py",
        '            self._expect_nothing(self._exchange_locked("", timeout_s=rest), f"<CR after {command}>")\n',
        "            pass\n",
        ("tests/drivers/test_puma_transcript.py::test_one_noise_prompt_does_not_end_a_motion",),
        "a motion counts as complete at the first prompt character (one noise byte ends it early)",
    ),
    Mutation(
        "ctrl-c-not-130",
        "procedures/cli.py",
        '    (Cancelled, EXIT_INTERRUPTED, "the run was interrupted; the cell was left as stated above"),\n',
        "",
        ("tests/procedures/test_engine.py::test_ctrl_c_during_selfview_park_exits_130",),
        "Ctrl-C during a procedure exits 1 ('this is a bug') instead of 130",
    ),
    # --- one per safety rule: the gripper, files and pictures --------------------------------------------
    Mutation(
        "poller-feeds-watchdog-after-failure",
        "drivers/pneumatic_gripper/gripper.py",
        "            if self._halted is not None or self._lost is not None:\n"
        "                return  # the safe-state rule: after a failure nothing feeds the watchdog until connect()\n"
        "            try:\n"
        "                self._read_raw(reconnect=False)\n",
        "            try:\n"
        "                self._read_raw()\n",
        ("tests/drivers/test_gripper_terminal.py::test_no_watchdog_feed_after_a_failed_command",),
        "the poller reconnects and keeps the valve terminal's watchdog fed after the driver gave up",
    ),
    Mutation(
        "stroke-outputs-not-read-back",
        "drivers/pneumatic_gripper/gripper.py",
        "                        self._confirm_outputs(want, target)\n",
        "                        pass\n",
        ("tests/drivers/test_gripper_transcript.py::test_stroke_with_outputs_reset_by_the_terminal_is_a_fault",),
        "a stroke is confirmed by the reed switches while the terminal has reset the valve outputs",
    ),
    Mutation(
        "stroke-confirmed-after-the-poller-gave-up",
        "drivers/pneumatic_gripper/gripper.py",
        "        while True:\n            self._check_undisturbed(target)\n",
        "        while True:\n",
        ("tests/drivers/test_gripper_transcript.py::test_poller_losing_the_link_during_a_stroke_fails_the_stroke",),
        "a stroke reconnects and confirms after the poller lost the link and the safe state is being applied",
    ),
    Mutation(
        "stray-coil-left-on",
        "drivers/pneumatic_gripper/gripper.py",
        "            self.link.write_coil(address, False)\n",
        "            pass\n",
        ("tests/drivers/test_gripper_transcript.py::test_write_echo_naming_another_coil_switches_it_off_on_a_dedicated_terminal",),
        "a coil a corrupted write switched on is left on though the io map says the terminal is this gripper's alone",
    ),
    Mutation(
        "reed-contradiction-accepted",
        "drivers/pneumatic_gripper/gripper.py",
        "        if self.open_sensor and self.closed_sensor:\n"
        '            raise GripperFault("both reed switches (open and closed) are on: a switch is broken or mis-wired")\n',
        "",
        ("tests/drivers/test_gripper_transcript.py::test_both_switches_on_is_a_fault",),
        "both reed switches on is taken as a jaw state",
    ),
    Mutation(
        "one-reading-confirms-a-stroke",
        "drivers/pneumatic_gripper/gripper.py",
        "                if seen_target:  # two consecutive readings agree: a single corrupted reply cannot confirm\n",
        "                if True:\n",
        ("tests/drivers/test_gripper_transcript.py::test_one_flipped_bit_neither_confirms_nor_faults",),
        "a single (possibly corrupted) reading confirms a jaw motion",
    ),
    Mutation(
        "yaml-aliases-accepted",
        "selfview/files/io_safe.py",
        "            if self.check_event(yaml.AliasEvent):\n",
        "            if False and self.check_event(yaml.AliasEvent):\n",
        ("tests/selfview/test_calfile.py::test_hostile_yaml_is_refused_at_once",),
        "YAML aliases accepted in calibration and cell files (a 491-byte alias bomb hangs the command)",
    ),
    Mutation(
        "picture-size-unchecked",
        "selfview/files/io_safe.py",
        "    if w > max_side or h > max_side or w * h > max_pixels:\n",
        "    if False:\n",
        ("tests/selfview/test_io_safe.py::test_a_huge_png_is_refused_from_its_header",),
        "a picture is decoded whatever size its header declares",
    ),
    Mutation(
        "tiff-directory-looked-for-in-the-first-64-kib",
        "selfview/files/io_safe.py",
        "        fmt, w, h = picture_size(blob)\n",
        "        fmt, w, h = picture_size(blob[:65536])\n",
        ("tests/selfview/test_io_safe.py::test_a_tiff_is_sized_from_its_directory_after_the_pixels",),
        "a large TIFF (its directory written after its pixels, as libtiff does) refused as truncated",
    ),
    Mutation(
        "tiff-read-in-one-byte-order",
        "selfview/files/io_safe.py",
        '        num = lambda at, n=2: int.from_bytes(head[at : at + n], "little" if head[:1] == b"I" else "big")'
        "  # noqa: E731\n",
        '        num = lambda at, n=2: int.from_bytes(head[at : at + n], "little")  # noqa: E731\n',
        ("tests/selfview/test_io_safe.py::test_a_tiff_is_sized_from_its_directory_after_the_pixels",),
        "a big-endian TIFF (a Motorola-order camera's) sized from its bytes read backwards: refused or misread",
    ),
    Mutation(
        "end-of-frame-stamp-as-exposure",
        "drivers/frame_grabber_v4l2/capture.py",
        '    return ts if tstamp == "start" else ts - buffer_s\n',
        "    return ts\n",
        ("tests/drivers/test_grabber_v4l2.py::test_a_frame_ending_after_settling_but_exposed_before_is_dropped",),
        "V4L2's end-of-frame timestamp taken as the start of exposure (a frame exposed before settling passes)",
    ),
    # --- safety rules: the engine's cleanup, the drivers' checks, the files' refusals ---------------------------
    Mutation(
        "engine-closes-stop-at-first-failure",
        "procedures/engine.py",
        'rep[f"{nm}_close"] = f"close failed: {exc}"',
        'rep[f"{nm}_close"] = f"close failed: {exc}"; break',
        ("tests/procedures/test_engine.py::test_every_device_is_closed_when_one_close_fails",),
        "the engine's cleanup stops closing the devices at the first close that fails (the others stay open)",
    ),
    Mutation(
        "engine-cancel-unchecked-between-steps",
        "procedures/engine.py",
        "        if self.cancel.is_set():\n            raise Cancelled(\"run cancelled\")\n        self._n += 1\n",
        "        if False:\n            raise Cancelled(\"run cancelled\")\n        self._n += 1\n",
        ("tests/procedures/test_engine.py::test_no_step_starts_after_a_cancellation",),
        "a cancellation is not checked before the next step (the next motion starts after Ctrl-C)",
    ),
    Mutation(
        "engine-cleanup-only-for-project-errors",
        "procedures/engine.py",
        'self.cleanup(f"{type(exc).__name__}: {exc}", worker_stopped=True)',
        'isinstance(exc, CellError) and self.cleanup(f"{type(exc).__name__}: {exc}", worker_stopped=True)',
        ("tests/procedures/test_engine.py::test_cleanup_runs_for_an_exception_outside_the_projects_errors",),
        "the cleanup (ABORT, safe valve, closes) runs only for the project's own errors, not for any other exception",
    ),
    Mutation(
        "motion-arrival-ignores-orientation",
        "drivers/puma_val_serial/driver.py",
        "if mm > lim.arrival_tol_mm or deg > lim.arrival_tol_deg:",
        "if mm > lim.arrival_tol_mm:",
        ("tests/drivers/test_puma_transcript.py::test_a_motion_that_ends_turned_from_its_target_is_not_arrived",),
        "a Cartesian motion's arrival check drops its orientation condition (an arm turned away passes as arrived)",
    ),
    Mutation(
        "valve-safe-confirmed-without-read-back",
        "drivers/pneumatic_gripper/gripper.py",
        "outputs = self._read_outputs_agreed()",
        "outputs = dict(want)",
        ("tests/drivers/test_gripper_transcript.py::test_single_solenoid_safe_state",),
        "the valve's safe state reported as confirmed from what was written, without reading the outputs back",
    ),
    Mutation(
        "register-write-echo-unchecked",
        "drivers/pneumatic_gripper/modbus.py",
        'self._check_echo(what, rsp, (address, int(value)), "holding_register")',
        "pass",
        ("tests/drivers/test_gripper_transcript.py::test_a_register_write_whose_echo_differs_is_a_protocol_error",),
        "a holding register write's echo is not compared with the address and value sent",
    ),
    Mutation(
        "calfile-without-checksum-accepted",
        "selfview/files/calfile.py",
        "if want != doc_checksum(body):",
        "if want is not None and want != doc_checksum(body):",
        ("tests/selfview/test_calfile.py::test_a_file_without_a_checksum_is_refused",),
        "a calibration file with no checksum at all is accepted (only a wrong one is refused)",
    ),
    # --- safety on every entry point: signals, ownership, stalls, paths, stale state --------------------------
    Mutation(
        "signal-inherited-ignored-taken",
        "drivers/signals.py",
        "            if signal.getsignal(sig) is _default(sig):\n",
        "            if signal.getsignal(sig) in (_default(sig), signal.SIG_IGN):\n",
        ("tests/drivers/test_lab_script_signals.py::test_a_signal_inherited_as_ignored_stays_ignored",),
        "a signal the program inherited as ignored (nohup) is taken over: closing the terminal stops the script",
    ),
    Mutation(
        "lab-script-robot-not-stopped-on-a-signal",
        "drivers/puma_val_serial/driver.py",
        "                signals.watch(self)  # a termination signal ABORTs the arm, whichever thread drives it\n",
        "                pass\n",
        ("tests/drivers/test_lab_script_signals.py::test_a_termination_signal_stops_the_arm_and_makes_the_valve_safe_in_any_thread",),
        "a script driving PumaVAL itself (or a session in a worker thread) gets no ABORT on SIGTERM, SIGHUP or Ctrl-C",
    ),
    Mutation(
        "gripper-command-outside-the-engine",
        "procedures/commands/gripper.py",
        "            _switch(gripper, args.action)\n",
        '            getattr(gripper, {"open": "open_jaws", "close": "close_jaws", "safe": "safe"}[args.action])()\n',
        ("tests/drivers/test_gripper_cli.py::test_a_signal_during_a_jaw_stroke_leaves_the_valve_safe_and_says_so",),
        "selfview gripper open|close switches the valve outside the engine: a signal leaves it energised",
    ),
    Mutation(
        "engine-jaw-wait-not-interrupted",
        "procedures/engine.py",
        "                    interrupt()\n",
        "                    pass\n",
        ("tests/drivers/test_gripper_cli.py::test_a_signal_during_a_jaw_stroke_leaves_the_valve_safe_and_says_so",),
        "on a signal the jaw wait goes on to its own timeout: the valve stays energised meanwhile",
    ),
    Mutation(
        "motion-wait-formula-inverted",
        "drivers/puma_val_serial/limits.py",
        "(t_at_100 / s + self.accel_s)",
        "(t_at_100 * s + self.accel_s)",
        ("tests/drivers/test_puma_cli.py::test_a_slow_motion_longer_than_the_margin_is_waited_for_to_its_end",),
        "the motion wait multiplied by the speed instead of divided: a slow motion ends in a false timeout and ABORT",
    ),
    Mutation(
        "motion-wait-formula-loose",
        "drivers/puma_val_serial/limits.py",
        "+ self.accel_s) + self.timeout_margin_s",
        "+ self.accel_s) + self.timeout_margin_s + 5.0",
        ("tests/drivers/test_puma_cli.py::test_a_stalled_reply_line_gets_abort_within_5_s_of_the_motions_expected_end",),
        "the motion wait 5 s longer: a stalled reply line gets its ABORT too late",
    ),
    Mutation(
        "stall-reply-judged-at-the-deadline",
        "drivers/puma_val_serial/driver.py",
        "self._overtime_end = now + _OVERTIME_S\n            return False",
        "self._overtime_end = now + _OVERTIME_S\n            return True",
        ("tests/drivers/test_puma_cli.py::test_a_stall_of_the_host_longer_than_the_reply_limit_is_no_device_fault",
         "tests/drivers/test_puma_host_stall.py::test_a_reply_that_arrived_while_the_host_was_stopped_after_a_silent_read_counts"),
        "a reply that arrived complete while the host was stalled is a device fault: ABORT and exit 4",
    ),
    Mutation(
        "abort-confirmation-judged-at-the-deadline",
        "drivers/puma_val_serial/driver.py",
        "                if limit.passed(chunk):  # a line that keeps talking ends the wait too",
        "                if time.monotonic() >= limit.deadline:",
        ("tests/drivers/test_puma_host_stall.py::"
         "test_an_abort_confirmed_while_the_host_was_stopped_after_a_silent_read_counts_as_confirmed",),
        "an ABORT the controller confirmed while the host was stalled is reported unconfirmed",
    ),
    Mutation(
        "valve-recorded-after-its-write",
        "drivers/pneumatic_gripper/gripper.py",
        "        if on:  # written ahead",
        "        if False:  # written ahead",
        ("tests/drivers/test_stale_state.py::test_the_energised_valve_is_recorded_before_the_write_that_energises_it",),
        "a host that dies between the valve's write and its answer leaves no record: the next run goes on",
    ),
    Mutation(
        "lock-keyed-on-the-spelling",
        "drivers/_ownership.py",
        'return cls(kind, f"{host}:{port}", lambda: host_identity(host, port))',
        'return cls(kind, f"{host}:{port}")',
        ("tests/drivers/test_ownership.py::test_the_valve_terminals_lock_is_keyed_on_the_address_not_its_spelling",),
        "the valve terminal's lock keyed on how its address is written: localhost drives a terminal another holds",
    ),
    Mutation(
        "lock-file-follows-links",
        "selfview/files/lockdir.py",
        "os.O_NOFOLLOW | ",
        "",
        ("tests/drivers/test_ownership.py::test_a_planted_link_in_the_lock_folder_is_not_followed",),
        "a lock file opened through a planted link truncates the file it points to",
    ),
    Mutation(
        "lock-folder-mode-unchecked",
        "selfview/files/lockdir.py",
        "    if stat.S_IMODE(st.st_mode) & 0o077:\n",
        "    if False:\n",
        ("tests/drivers/test_ownership.py::test_a_lock_folder_others_may_use_is_refused_by_name",),
        "a lock folder others may write is used",
    ),
    Mutation(
        "stale-record-ignored",
        "drivers/_ownership.py",
        "        if busy and not clear_stale:\n",
        "        if False:\n",
        ("tests/drivers/test_stale_state.py",),
        "a program killed during a motion or with the valve energised goes unnoticed by the next one",
    ),
    Mutation(
        "stdout-gone-exits-0",
        "procedures/cli.py",
        "            return 128 + signal.SIGPIPE\n",
        "            return EXIT_OK\n",
        ("tests/procedures/test_cli_calibrate_track.py::test_monitor_whose_output_goes_away_ends_non_zero_after_the_cleanup",),
        "monitor | head -1 ends with 0 after one frame of twelve",
    ),
    Mutation(
        "rtu-reads-tried-once",
        "drivers/pneumatic_gripper/modbus.py",
        "tries = self.retries + 1 if idempotent else 1",
        'tries = self.retries + 1 if idempotent and self.url.transport == "tcp" else 1',
        ("tests/drivers/test_gripper_terminal.py::test_rtu_reads_are_tried_again_like_tcp_writes_never",),
        "a Modbus RTU read whose reply was lost is not tried again",
    ),
    Mutation(
        "monitor-apply-without-compare-and-swap",
        "procedures/commands/monitor.py",
        "save_calibration(cal, args.calibration, expected=started)",
        "save_calibration(cal, args.calibration)",
        ("tests/procedures/test_cli_calibrate_track.py::test_monitor_apply_never_overwrites_a_file_changed_since_it_was_read",),
        "monitor --apply overwrites a calibration file another program updated during the run",
    ),
    Mutation(
        "track-apply-without-compare-and-swap",
        "procedures/commands/track.py",
        "save_calibration(cal, args.calibration, expected=cal)",
        "save_calibration(cal, args.calibration)",
        ("tests/procedures/test_cli_calibrate_track.py::test_track_apply_never_overwrites_a_file_changed_since_it_was_read",),
        "track --apply overwrites a calibration file another program updated since it was read",
    ),
    Mutation(
        "camfile-nan-covariance-accepted",
        "selfview/files/camfile.py",
        "np.all(np.isfinite(cov)) and ",
        "",
        ("tests/selfview/test_intrinsics.py::test_a_camera_file_whose_covariance_holds_nan_is_refused",),
        "a camera file whose covariance holds NaN is accepted (only its sigmas are checked)",
    ),
    # --- issue 32: a line end put inside a typed motion line (val.h2d.error_line) --------------------------------
    Mutation(
        "val-appro-distance-bare",
        "drivers/puma_val_serial/dialect.py",
        '    "appro": "DO APPRO {name}, ({d})",\n',
        '    "appro": "DO APPRO {name}, {d}",\n',
        ("tests/drivers/test_puma_line_prefixes.py::test_no_proper_prefix_of_a_motion_speed_or_location_line_is_a_valid_line",),
        "APPRO's distance written bare again: 'DO APPRO plate, 5', a cut 'DO APPRO plate, 50', is a shorter motion",
    ),
    Mutation(
        "val-parser-closing-parenthesis-optional",
        "drivers/puma_val_serial/dialect.py",
        r'inner + "".join(rf"(?({n})\s*\))" for n in reversed(names))',
        r'inner + "".join(rf"(?:\s*\))?" for n in reversed(names))',
        ("tests/drivers/test_puma_line_prefixes.py", "tests/mocks/test_val_controller.py::test_a_line_cut_short_by_a_line_end_runs_nothing"),
        "the controller's parser does not insist on the closing parenthesis: 'DO APPRO plate, (5' runs",
    ),
    # --- issue 32's planted bugs that no test saw: the grab's moment, NaN residuals, a lying size, an escape -------
    Mutation(
        "engine-grab-without-after",
        "procedures/engine.py",
        'frame = d.camera.grab(after=time.monotonic(), average=int(p.get("average", 1)))',
        'frame = d.camera.grab(average=int(p.get("average", 1)))',
        ("tests/procedures/test_engine.py::test_the_grab_step_asks_for_a_frame_exposed_after_the_step_began",),
        "the engine's grab loses its after=: a frame exposed before the robot settled is used",
    ),
    Mutation(
        "policy-nan-residual-updates",
        "selfview/estimation/policy.py",
        "        if not est.rms_px <= lim.max_rms_px:\n",
        "        if est.rms_px > lim.max_rms_px:\n",
        ("tests/selfview/test_policy.py::test_an_estimate_or_a_recalibration_whose_residual_is_nan_is_an_alarm_not_a_new_C_H_G",),
        "an update whose residual is NaN passes the residual check and becomes C_H_G",
    ),
    Mutation(
        "policy-nan-residual-recalibrates",
        "selfview/estimation/policy.py",
        "        if not est_R.rms_px <= lim.max_rms_px:\n",
        "        if est_R.rms_px > lim.max_rms_px:\n",
        ("tests/selfview/test_policy.py::test_an_estimate_or_a_recalibration_whose_residual_is_nan_is_an_alarm_not_a_new_C_H_G",),
        "a recalibration whose residual is NaN passes the residual check and becomes C_H_G",
    ),
    Mutation(
        "bounded-read-without-its-bound",
        "selfview/files/io_safe.py",
        "        while len(data) <= limit and (chunk := os.read(fd, limit + 1 - len(data))):\n",
        "        while chunk := os.read(fd, 65536):\n",
        ("tests/selfview/test_io_safe.py::test_a_bounded_read_stops_at_its_bound_on_a_file_whose_size_lies",),
        "the bounded reader reads to the end of a file whose size lies (a /proc file, a FUSE mount): without end",
    ),
    Mutation(
        "engine-signal-flag-takes-no-signal",
        "procedures/engine.py",
        "                    self._old[sig] = signal.signal(sig, self._note)\n",
        "                    pass\n",
        ("tests/procedures/test_engine.py",),
        "the engine's run takes no termination signal: it reaches the test process, where it must fail a test, "
        "not end the run (tests/conftest.py's SignalEscaped)",
    ),
)

_IGNORE = shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", "build", ".pytest_cache", "*.pyc", ".ci-*")
# pytest's exit codes that do not mean "a test failed": interrupted, internal error, usage, no tests
_NOT_A_FAILURE = {2, 3, 4, 5}


def copy_tree(dest: Path, root: Path = ROOT) -> Path:
    """The repository's tree (kernels built in place included) copied to ``dest``; returns it. The copy
    runs the same code: ``selfview/__init__.py`` resolves ``selfview.drivers`` and the others to the
    copy's folders."""
    shutil.copytree(root, dest, ignore=_IGNORE, symlinks=True)
    return dest


def apply(m: Mutation, tree: Path) -> str | None:
    """Put ``m`` into the tree; the reason it cannot be applied, or None."""
    path = tree / m.file
    if not path.is_file():
        return f"no longer applies: {m.file} does not exist"
    text = path.read_text(encoding="utf-8")
    n = text.count(m.original)
    if n != 1:
        where = "not found" if n == 0 else f"found {n} times"
        return f"no longer applies: the original text is {where} in {m.file}"
    path.write_text(text.replace(m.original, m.replacement), encoding="utf-8")
    return None


def _failed_tests(output: str) -> list[str]:
    return sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", output, flags=re.M)))


def run_one(m: Mutation, timeout_s: float, root: Path = ROOT) -> dict:
    """Apply ``m`` to a fresh copy of the tree, run its tests there, and say whether they caught it.

    ``python -m pytest -x -q -p no:cacheprovider <tests>`` in the copy, under a timeout. Caught means the
    tests failed (a non-zero exit other than "no tests collected" or a usage error). A mutation whose
    original text is not found, or found more than once, is reported with an error ("no longer applies")
    and never counted as caught; a run that times out counts as not caught, with its error."""
    t0 = time.monotonic()
    rec = {"name": m.name, "file": m.file, "caught": False, "failed_tests": [], "error": None}
    with tempfile.TemporaryDirectory(prefix="selfview-mutation-") as tmp:
        tree = copy_tree(Path(tmp) / "tree", root)
        why = apply(m, tree)
        if why is not None:
            rec["error"] = why
        else:
            env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
            cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *m.tests]
            try:
                out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout_s)
            except subprocess.TimeoutExpired:
                rec["error"] = f"the tests did not finish within {timeout_s:g} s"
            else:
                text = out.stdout + out.stderr
                if out.returncode in _NOT_A_FAILURE:
                    tail = " | ".join(text.strip().splitlines()[-3:])
                    rec["error"] = f"pytest exit code {out.returncode} (no test failure): {tail}"
                else:
                    rec["caught"] = out.returncode != 0
                    rec["failed_tests"] = _failed_tests(text)
    rec["seconds"] = round(time.monotonic() - t0, 1)
    return rec


def main(argv=None, mutations: tuple[Mutation, ...] = MUTATIONS, root: Path = ROOT) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", metavar="NAME", help="run only this mutation (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutation's test run (default 900)")
    args = ap.parse_args(argv)
    names = [m.name for m in mutations]
    if args.only:
        unknown = [n for n in args.only if n not in names]
        if unknown:
            ap.error(f"unknown mutation(s) {', '.join(unknown)}; known: {', '.join(names)}")
        chosen = [m for m in mutations if m.name in args.only]
    else:
        chosen = list(mutations)
    if args.list:
        print(json.dumps({"mutations": [{"name": m.name, "file": m.file, "tests": list(m.tests), "why": m.why}
                                        for m in chosen]}, indent=1))
        return 0
    results = []
    for m in chosen:
        print(f"mutation {m.name} ...", file=sys.stderr, flush=True)
        results.append(run_one(m, args.timeout, root))
    caught = sum(r["caught"] for r in results)
    print(json.dumps({"caught": caught, "total": len(results), "errors": sum(r["error"] is not None for r in results),
                      "mutations": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
