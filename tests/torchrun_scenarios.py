"""Run by tests/test_distributed.py, in one process or under torchrun: scripts/scenarios.py with each
case's diagnosis replaced by a cheap deterministic row (a function of the case alone, plus the rank
that ran it), so the test sees how the suite shares out, saves and gathers cases, not the diagnosis."""
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from helpers import load_script  # noqa: E402


def fake_case(case: dict, a, out, diagnose) -> dict:
    time.sleep(0.05)
    snr = 5.0 + 3.0 * case["size"] + case["seed"]
    return {"case": case["case"], "effect": case["effect"], "kind": "null" if case["effect"] == "none" else "library",
            "band": "null" if case["effect"] == "none" else "<10", "snr": snr, "snr_after_base": snr / 2,
            "correct": True, "decision": case["effect"], "rms_before": 1.0 + snr / 100, "rms_after": 1.0,
            "solves": 3, "seconds": 0.05, "solves_reused": 0, "rank": int(os.environ.get("RANK", "0"))}


if __name__ == "__main__":
    suite = load_script("scenarios")
    suite.run_case = fake_case
    suite.main(sys.argv[1:])
