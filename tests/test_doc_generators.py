"""The generators of README's and the docs' measured blocks that run commands rather
than library code: what they compare and how they report it (their runs are the
blocks themselves, `python -m experiments.regenerate_docs`)."""

import numpy as np

from experiments import (
    blocks,
    distributed_timing,
    regenerate_docs,
    requirements_methods,
    vehicles,
)


def test_the_distributed_check_counts_arrays_equal_bit_for_bit(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    a = np.arange(6, dtype=np.float32)
    np.savez(one / "draws.npz", x=a, y=a * 2, z=a)
    np.savez(two / "draws.npz", x=a, y=a * 2, z=a)
    assert distributed_timing.equal_arrays(one, two) == (3, 3)
    np.savez(two / "draws.npz", x=a, y=np.nextafter(a * 2, 100), w=a)  # z missing, w new
    assert distributed_timing.equal_arrays(one, two) == (1, 4)


def _run(method, full, passed):
    summary = {"passed": passed, "draws": 128, "yield": passed / 128, "interval": [0.9, 1.0]}
    return {
        "method": method,
        "command": f"fojax tune --requirements R --method {method} --quiet --out DIR",
        "command_s": 97.4,
        "tuning_s": 86.2,
        "first_full_validation": full,
        "returned_step": 22,
        "draw_steps": 1.13e8,
        "heldout": {
            "draws": 128,
            "horizon_s": 10.0,
            "initial": {**summary, "passed": 0, "yield": 0.0, "failures": {}, "objective": 1.29e5},
            "tuned": {**summary, "failures": {"tracking": 1, "tilt": 0}, "objective": 153.2},
        },
    }


def test_the_methods_table_marks_the_default_and_a_run_never_at_full_yield():
    text = requirements_methods.table(
        [_run("auto", {"step": 22, "wall_time_s": 26.0}, 127), _run("adam", None, 116)]
    )
    assert "--method M --quiet" in text and "on 128 draws x 10 s" in text
    assert "| `auto` (the default) | 97 | 86 | 22, 26 | 22 | 127/128, 99.2 % " in text
    assert "failures: 1 on tracking |" in text and "tilt" not in text
    assert "| `adam` | 97 | 86 | never | 22 | 116/128" in text
    assert "(start 0/128)" in text and "(start 1.29e+05)" in text


def test_a_block_reuses_results_only_where_its_folder_holds_files(tmp_path, monkeypatch):
    monkeypatch.setattr(blocks, "ROOT", tmp_path)
    block = blocks.Block("b", "d.md", ("python", "-c", "0"), (), results="results/b")
    assert not regenerate_docs._reused(block)
    (tmp_path / "results" / "b" / "runs").mkdir(parents=True)
    assert not regenerate_docs._reused(block)  # folders alone hold nothing to reuse
    (tmp_path / "results" / "b" / "runs" / "r.json").write_text("{}")
    assert regenerate_docs._reused(block)
    assert not regenerate_docs._reused(blocks.Block("c", "d.md", ("python",), ()))


def _vehicle_study(diverged: int, passed: int, chatter: float) -> dict:
    requirements = {"passed": passed, "draws": 64, "yield": passed / 64, "interval": [0.9, 1.0],
                    "failures": {"torque chattering": 64 - passed, "tilt": 0},
                    "diverged": diverged}  # fmt: skip
    row = {"diverged": diverged, "draws": 64, "position_rmse": None if diverged == 64 else 0.0334,
           "requirements": requirements, "torque_chattering_median": chatter}  # fmt: skip
    actuators = {"rotor_limited": True, "rotor_speed_limit_rad_s": 2272.7,
                 "thrust_to_weight": 2.248}  # fmt: skip
    return {"horizon_s": 80.0, "actuators": actuators, "controllers": {"afonftsmc": row, "fl": row}}


def test_the_vehicles_table_reads_each_study_and_marks_what_diverged():
    heldout = {"draws": 32, "horizon_s": 10.0,
               "initial": {"score": 1000.0, "diverged": 32},
               "tuned": {"score": 0.1277, "diverged": 0}}  # fmt: skip
    tuning = {"steps": 234, "tuning_s": 105.2, "heldout": heldout}
    run = {
        "vehicle": "examples/vehicles/crazyflie.toml",
        "requirements": "examples/requirements/crazyflie.toml",
        "tuning": {"afonftsmc": tuning, "fl": tuning},
        "paper": _vehicle_study(0, 0, 0.01), "paper_sign": _vehicle_study(64, 0, 0.01),
        "paper_full": _vehicle_study(64, 0, 0.01), "tuned": _vehicle_study(0, 64, 0.00488),
        "tuned_sign": _vehicle_study(0, 0, 0.02), "tuned_full": _vehicle_study(0, 64, 0.00488),
    }  # fmt: skip
    text = vehicles.table({"vehicles": {"crazyflie": run}})
    assert "rotor-limited at 2273 rad/s (thrust-to-weight 2.25)" in text
    assert "(32 draws x 10 s, `sat`)" in text and "bound 0.0064 N m/s" in text
    paper = "| afonftsmc | 0/64, 0.0 % (90.0-100.0 %), failures: 64 on torque chattering | "
    assert paper + "0/64, 0.0 % (90.0-100.0 %), failures: 64 on torque chattering; 64 " \
        "diverged | none: 64 diverged |" in text
    assert "| afonftsmc | 234, 105 | 0.1277 (1e+03, 32 diverged) | 64/64, 100.0 % " in text
    assert "| 0.0334 | 0.00488 |" in text and "| no switching |" in text
    assert "--vehicle examples/vehicles/V.toml" in text and "--controller C" in text
