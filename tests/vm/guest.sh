#!/bin/sh
# Runs inside the vm stage's guest (tests/vm/test_vm_stage.py boots it): loads vivid, then runs the
# device contract suites in one Python process against vivid and the two UARTs (and the robot's BREAK
# cases), and writes the results, the log and the exit status into OUT (the guest's only writable
# folder shared with the host).
# Usage: guest.sh OUT PYTHON ROBOT_URL GRIPPER_URL GRABBER_URL
out="$1"; python="$2"
up() { cut -d' ' -f1 /proc/uptime; }
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"  # this tree's selfview, whatever is installed
echo "boot $(up)" > "$out/timing"
modprobe vivid n_devs=1 node_types=0x1 input_types=0xe4 > "$out/modprobe.log" 2>&1
echo "vivid $(up)" >> "$out/timing"
dmesg | grep -E "ttyS|vivid" > "$out/dmesg.log" 2>&1
v4l2-ctl -d /dev/video0 -L > "$out/controls.txt" 2>&1
# the robot's line goes through the host's relay, which injects the BREAKs guest_serial_break.py asks for
SELFVIEW_PUMA_URL="$3" SELFVIEW_GRIPPER_URL="$4" SELFVIEW_GRABBER_URL="$5" SELFVIEW_VM_BREAK_RELAY=1 \
    PYTHONDONTWRITEBYTECODE=1 "$python" -m pytest -p no:cacheprovider -q -rA -s --junitxml="$out/guest.xml" \
    -k "real_controller or test_contract_ or test_grabber_device or serial_break" \
    tests/drivers/test_puma_contract.py tests/vm/guest_serial_break.py tests/drivers/test_gripper_terminal.py \
    tests/drivers/test_grabber_device.py \
    > "$out/guest.log" 2>&1 < /dev/null
echo $? > "$out/status"
echo "done $(up)" >> "$out/timing"
