"""A spring at the application's own loop rate (capi/examples/spring.c in
Python): the end-effector is pulled towards a point 80 mm off where it
starts, F = k (target - p), at most 3 N. Prints the loop rate and the state
age, and one line per 20 loops of what the device rendered.

    python3 python/examples/spring.py [PORT | --virtual] [--seconds S] [--heartbeat-ms MS]
"""

import argparse
import math
import time

import spidar

K_N_PER_MM = 0.02
F_MAX_N = 3.0


def wait_armed(dev, want):
    for _ in range(5000):
        s = dev.wait_state(2000)
        if s["armed"] == want and (want or not s["motors_on"]):
            return s
    raise SystemExit(f"spring: the device never reported armed={want}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("port", nargs="?")
    ap.add_argument("--virtual", action="store_true")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--heartbeat-ms", type=int, default=0)
    a = ap.parse_args()
    if a.port and not a.virtual:
        dev = spidar.Device.open(a.port)
    else:
        dev = spidar.Device.open_virtual(heartbeat_timeout_ms=a.heartbeat_ms)
    with dev:
        info = dev.info()
        print("device %s firmware %d.%d.%d loop %d us" % (
            info["device_id"], *info["firmware_version"], info["loop_period_us"]))
        s = dev.wait_state(5000)
        target = [s["position_mm"][0] + 80.0, s["position_mm"][1], s["position_mm"][2]]
        print("target %.3f %.3f %.3f" % tuple(target))
        dev.arm()
        dev.set_force(0.0, 0.0, 0.0)
        s = wait_armed(dev, True)
        print("armed %d" % s["armed"])
        t_end = s["time_us"] + int(a.seconds * 1e6)
        ages = []
        t0 = time.monotonic()
        while True:
            s = dev.state()
            if s["time_us"] >= t_end:
                break
            f = [K_N_PER_MM * (t - p) for t, p in zip(target, s["position_mm"])]
            norm = math.sqrt(sum(x * x for x in f))
            if norm > F_MAX_N:
                f = [x * F_MAX_N / norm for x in f]
            dev.set_force(*f)
            ages.append(s["age_us"])
            if len(ages) % 20 == 0:
                p, r = s["position_mm"], s["rendered_force_n"]
                print("state %d %d %.3f %.3f %.3f %.4f %.4f %.4f" % (
                    s["time_us"], s["armed"], *p, *r))
        wall = time.monotonic() - t0
        ages.sort()
        print("loop_hz %.1f" % (len(ages) / wall))
        print("state_age_us median %d p99 %d" % (
            ages[len(ages) // 2] if ages else 0, ages[len(ages) * 99 // 100] if ages else 0))
        dev.set_force(0.0, 0.0, 0.0)
        dev.disarm()
        s = wait_armed(dev, False)
        print("disarmed %d" % (not s["armed"] and not s["motors_on"]))
        print('faults "%s"' % ",".join(s["faults"]))
        ls = dev.link_stats()
        print("link states %d lost %d device_dropped %d rejected %d" % (
            ls["states"], ls["lost"], ls["device_dropped"], ls["rejected"]))


if __name__ == "__main__":
    main()
