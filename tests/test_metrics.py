"""Metrics on hand-computed episodes: SPL, the L>=5 bucket, Done / failed-action rates, exploration
ratio, bootstrap intervals and the report cells."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapless.cli import main
from mapless.evaluate.metrics import (
    METRICS,
    EpisodeResult,
    Metric,
    aggregate,
    compared_metrics,
    exploration_curve,
    exploration_ratio,
    in_l5,
    main_metrics,
    register,
    sightings,
    spl,
    summarize,
)
from mapless.evaluate.report import (
    comparison_table,
    details_table,
    format_difference,
    format_estimate,
    model_record,
    model_table,
)
from mapless.evaluate.stats import bootstrap_ci, difference_estimates, mean_std, seed_estimates


def ep(index, success, length, optimal, done=True, failed=0, poses=None, room="kitchen") -> EpisodeResult:
    poses = tuple(poses) if poses is not None else tuple(range(1, length + 1))
    assert len(poses) == length
    return EpisodeResult(
        index=index, episode_id=f"e{index}", scene="FloorPlan1" if room == "kitchen" else "FloorPlan201",
        room_type=room, target="Mug", success=success, length=length, optimal_length=optimal, called_done=done,
        failed_actions=failed, reward=0.0, start_pose=0, poses=poses,
    )  # fmt: skip


def test_spl_hand_values():
    # Optimal 4 actions (3 moves + Done) taken in 8: SPL 0.5. Exactly optimal: 1. Failure: 0.
    assert spl(True, 8, 4) == 0.5
    assert spl(True, 4, 4) == 1.0
    assert spl(False, 4, 4) == 0.0
    # The max() clamp: a (simulator-inconsistent) shorter-than-optimal success still scores 1, not 2.
    assert spl(True, 2, 4) == 1.0
    # Unknown optimal length (SAVN's best = inf): SPL 0, and the episode is in the L>=5 bucket too.
    assert spl(True, 5, -1) == 0.0
    assert in_l5(-1) and in_l5(5) and not in_l5(4)


def test_aggregate_hand_computed_set():
    results = [
        ep(0, True, 8, 4),  # SPL 0.5, not L>=5
        ep(1, True, 10, 5),  # SPL 0.5, L>=5
        ep(2, False, 100, 7, done=False, failed=10),  # timeout, L>=5
        ep(3, True, 6, 6, failed=0),  # SPL 1.0, L>=5
    ]
    m = aggregate(results)
    assert m["episodes"] == 4 and m["l5_episodes"] == 3
    assert m["success"] == pytest.approx(0.75)
    assert m["spl"] == pytest.approx((0.5 + 0.5 + 0 + 1.0) / 4)
    assert m["l5_success"] == pytest.approx(2 / 3)
    assert m["l5_spl"] == pytest.approx((0.5 + 0 + 1.0) / 3)
    assert m["ep_length"] == pytest.approx((8 + 10 + 100 + 6) / 4)
    assert m["done_rate"] == pytest.approx(0.75)
    assert m["false_done_rate"] == 0.0  # every Done here succeeded; the failure is a timeout
    assert m["failed_action_rate"] == pytest.approx(10 / 124)
    wrong = aggregate([*results, ep(4, False, 3, 5, done=True)])
    assert wrong["done_rate"] == pytest.approx(4 / 5) and wrong["false_done_rate"] == pytest.approx(1 / 5)


def test_savn_spl_equals_paper_spl_when_lengths_are_consistent():
    # SAVN: best / eps_len on success, no clamp. Equal to the paper's formula whenever L >= L*.
    rng = np.random.default_rng(0)
    for _ in range(200):
        optimal = int(rng.integers(2, 20))
        length = int(rng.integers(optimal, 101))
        assert spl(True, length, optimal) == pytest.approx(optimal / length)


def test_exploration_ratio_paper_example():
    # "if an agent only explores two states in the first five steps, the rate is 40 %"
    poses = [1, 1, 2, 2, 1]
    assert exploration_ratio(poses)[4] == pytest.approx(0.4)
    assert exploration_ratio(poses).tolist() == pytest.approx([1.0, 0.5, 2 / 3, 0.5, 0.4])


def test_exploration_curve_averages_running_episodes_only():
    a = ep(0, True, 2, 2, poses=[1, 2])  # ratios 1, 1
    b = ep(1, False, 4, 5, done=False, poses=[1, 1, 1, 1])  # ratios 1, .5, 1/3, .25
    mean, count = exploration_curve([a, b], horizon=5)
    assert count.tolist() == [2, 2, 1, 1, 0]
    assert mean[:4].tolist() == pytest.approx([1.0, 0.75, 1 / 3, 0.25])
    assert math.isnan(mean[4])


def test_summarize_per_room():
    results = [ep(0, True, 4, 4), ep(1, False, 200, 9, done=False, room="living_room")]
    s = summarize(results)
    assert set(s) == {"overall", "kitchen", "living_room"}
    assert s["kitchen"]["success"] == 1.0 and s["living_room"]["success"] == 0.0
    assert s["overall"]["success"] == 0.5


def test_bootstrap_interval_contains_mean_and_shrinks_with_n():
    rng = np.random.default_rng(1)
    small = (rng.random(100) < 0.4).astype(float)
    large = (rng.random(2000) < 0.4).astype(float)
    lo, hi = bootstrap_ci(small)
    assert lo < small.mean() < hi
    lo2, hi2 = bootstrap_ci(large)
    assert hi2 - lo2 < hi - lo
    # Binomial standard error: the 95 % half-width is about 1.96 * sqrt(p(1-p)/n).
    assert (hi2 - lo2) / 2 == pytest.approx(1.96 * math.sqrt(0.4 * 0.6 / 2000), rel=0.15)
    # Seeded: identical intervals on every call.
    assert bootstrap_ci(small) == (lo, hi)


def test_seed_estimates_mean_std_over_seeds():
    seed_a = [ep(i, i % 2 == 0, 4, 4) for i in range(10)]  # SR 0.5
    seed_b = [ep(i, i % 5 == 0, 4, 4) for i in range(10)]  # SR 0.2
    est = seed_estimates([seed_a, seed_b])
    assert est["success"].mean == pytest.approx(0.35)
    assert est["success"].std == pytest.approx(mean_std([0.5, 0.2])[1])
    assert est["success"].seeds == 2 and est["success"].episodes == 10
    assert est["success"].ci_low <= 0.35 <= est["success"].ci_high
    with pytest.raises(ValueError):
        seed_estimates([seed_a, seed_b[:5]])


def test_difference_of_two_models_is_paired_over_episodes():
    # B succeeds wherever A does, and on 40 more of the 400 episodes: a difference of exactly 0.1.
    a = [ep(i, i % 2 == 0, 4, 4) for i in range(400)]
    b = [ep(i, i % 2 == 0 or i % 10 == 1, 4, 4) for i in range(400)]
    diff = difference_estimates([a], [b])["success"]
    assert diff.mean == pytest.approx(0.1) and diff.episodes == 400
    # Paired, the resampled difference is the mean of 400 per-episode differences of which 40 are 1:
    # binomial, half-width 1.96 * sqrt(0.1 * 0.9 / 400) = 0.029 (unpaired it would be ~0.069).
    assert (diff.ci_high - diff.ci_low) / 2 == pytest.approx(1.96 * math.sqrt(0.1 * 0.9 / 400), rel=0.15)
    assert diff.ci_low > 0.05
    assert difference_estimates([a], [b])["success"] == diff  # seeded
    with pytest.raises(ValueError):
        difference_estimates([a], [b[:200]])


def test_difference_interval_carries_the_spread_over_seeds():
    # Two identical models whose two seeds score 0.2 and 0.6: no difference on average, but drawing
    # seeds can pit A's 0.2 against B's 0.6 (probability 1/16 each way), so the interval reaches ±0.4.
    seeds = [[ep(i, i % 5 == 0, 4, 4) for i in range(100)], [ep(i, i % 5 < 3, 4, 4) for i in range(100)]]
    diff = difference_estimates(seeds, seeds)["success"]
    assert diff.mean == pytest.approx(0.0) and diff.seeds_a == diff.seeds_b == 2
    assert diff.ci_low < -0.3 and diff.ci_high > 0.3
    # One seed each: only the episodes vary, and identical results differ by exactly nothing.
    same = difference_estimates(seeds[:1], seeds[:1])["success"]
    assert (same.ci_low, same.mean, same.ci_high) == (0.0, 0.0, 0.0)


def test_episodes_stored_without_poses_are_left_out_of_the_exploration_ratio_everywhere():
    # Ratios: [1, 2, 1] -> 1.0 (3 distinct of 3), [1, 1, 1, 1] -> 0.25; the third has no poses.
    results = [ep(0, True, 3, 3), ep(1, False, 4, 4, poses=[7, 7, 7, 7])]
    results.append(dataclasses.replace(ep(2, True, 5, 5), poses=()))
    assert aggregate(results)["exploration_ratio"] == pytest.approx((1.0 + 0.25) / 2)
    est = seed_estimates([results, results])["exploration_ratio"]
    assert est.mean == pytest.approx((1.0 + 0.25) / 2) and est.episodes == 2
    assert est.ci_low >= 0.25 and est.ci_high <= 1.0
    # No poses at all: unknown, not a warning-laden 0.
    bare = [dataclasses.replace(r, poses=()) for r in results]
    assert math.isnan(aggregate(bare)["exploration_ratio"])
    assert math.isnan(seed_estimates([bare])["exploration_ratio"].mean)


def test_sightings_are_the_first_step_that_sees_the_target_and_the_last_pose_in_frame():
    sees = np.zeros(8, dtype=bool)
    sees[[4, 6]] = True
    in_frame = sees.copy()
    in_frame[[2, 5]] = True  # in the frame, out of the rule's reach
    # Path 0, 1, 2, 4, 5, 6: first seen at step 3; actions are taken at 0, 1, 2, 4, 5: one on 4.
    assert sightings(sees, in_frame, 0, [1, 2, 4, 5, 6]) == (3, True, 1)
    # The start sees it, the agent walks away (one action at 6, one at 4): two stops passed.
    assert sightings(sees, in_frame, 6, [5, 4, 7]) == (0, False, 2)
    assert sightings(sees, in_frame, 0, [1, 1, 2]) == (-1, True, 0)  # never saw it; ends with it too far
    assert sightings(sees, in_frame, 0, []) == (-1, False, 0)  # no step taken


def test_stops_passed_count_the_actions_on_a_pose_where_done_would_have_succeeded():
    sees = np.zeros(8, dtype=bool)
    sees[[4, 5]] = True
    frame = sees.copy()
    # Path 0, 4, 5, 5: actions at 0 (move), 4 (move), 5 (a failed move), 5 (Done, a success): the
    # moves at 4 and 5 were stops passed up, the successful Done is not.
    assert sightings(sees, frame, 0, [4, 5, 5, 5], success=True).stops_passed == 2
    # The same path ended by the step limit instead: the last action at 5 was no Done, so 3.
    assert sightings(sees, frame, 0, [4, 5, 5, 5], success=False).stops_passed == 3
    # A success at its first sight passes none.
    assert sightings(sees, frame, 0, [4, 4], success=True).stops_passed == 0
    # Aggregated per episode over recorded episodes only.
    results = [
        dataclasses.replace(ep(0, True, 4, 4), first_seen=1, ended_in_frame=True, stops_passed=2),
        dataclasses.replace(ep(1, False, 4, 4), first_seen=1, ended_in_frame=True, stops_passed=3),
        ep(2, False, 4, 4),
    ]
    assert aggregate(results)["stops_passed"] == pytest.approx(2.5)
    assert math.isnan(aggregate(results[2:])["stops_passed"])


def test_seen_and_short_done_rates_count_recorded_episodes_only():
    # (success, called Done, first seen, ended in frame): a success; a timeout that saw it; a Done
    # with the target in the frame but too far; a Done with nothing in the frame; cached before both
    # were recorded.
    rows = [
        (True, True, 2, True),
        (False, False, 1, False),
        (False, True, -1, True),
        (False, True, -1, False),
    ]
    results = [
        dataclasses.replace(ep(i, s, 4, 4, done=d), first_seen=f, ended_in_frame=e)
        for i, (s, d, f, e) in enumerate(rows)
    ]
    results.append(ep(4, False, 4, 4))
    m = aggregate(results)
    assert m["seen_rate"] == pytest.approx(2 / 4) and m["success"] == pytest.approx(1 / 5)
    assert m["short_done_rate"] == pytest.approx(1 / 4) and m["false_done_rate"] == pytest.approx(3 / 5)
    assert seed_estimates([results])["seen_rate"].episodes == 4
    assert math.isnan(aggregate(results[4:])["seen_rate"])
    assert math.isnan(aggregate(results[4:])["short_done_rate"])
    # Approach: a success's actions from its first sight on (its Done included), successes only.
    assert m["approach_steps"] == pytest.approx(4 - 2)
    more = dataclasses.replace(ep(5, True, 7, 4), first_seen=0, ended_in_frame=True)  # seen at the start
    assert aggregate([*results, more])["approach_steps"] == pytest.approx((2 + 7) / 2)
    # Stored and read back whole, and an old record without the fields reads as unrecorded.
    assert EpisodeResult.from_dict(results[1].to_dict()) == results[1]
    old = results[1].to_dict()
    del old["first_seen"], old["ended_in_frame"], old["stops_passed"]
    assert EpisodeResult.from_dict(old) == dataclasses.replace(
        results[1], first_seen=None, ended_in_frame=None, stops_passed=None
    )


def test_report_cells_and_table():
    results = [ep(i, i < 3, 8, 4) for i in range(4)]
    record = model_record("cvmeta", [results])
    cell = format_estimate("success", record["estimates"]["success"])
    assert cell.startswith("75.0 [")  # one seed: no ±
    table = model_table([record])
    assert "| cvmeta | 75.0" in table and "SR L≥5" in table


def test_a_label_in_parts_fills_one_column_each_and_must_match_them():
    record = model_record("a3c | variants | shifted", [[ep(i, i < 3, 8, 4) for i in range(4)]])
    header, _, row = model_table([record], label=("model", "trained on", "tested on")).splitlines()
    assert header.split(" | ")[:4] == ["| model", "trained on", "tested on", "SR"]
    assert row.startswith("| a3c | variants | shifted | 75.0 [")
    assert header.count("|") == row.count("|")
    with pytest.raises(ValueError, match="3 parts, the table 1"):
        model_table([record])


def test_difference_cells_are_signed_points_for_rates_and_steps_for_lengths():
    rate = {"mean": -0.07, "ci_low": -0.112, "ci_high": 0.0291, "seeds_a": 3, "seeds_b": 3, "episodes": 400}
    assert format_difference("success", rate) == "-7.0 [-11.2, +2.9]"
    length = {**rate, "mean": 1.5, "ci_low": 0.5, "ci_high": 2.5}
    assert format_difference("ep_length", length) == "+1.5 [+0.5, +2.5]"
    assert format_difference("spl", {**rate, "mean": float("nan")}) == "–"


def test_compare_prints_b_minus_a_paired_on_the_same_episodes(tmp_path, capsys):
    """A run's evaluation cache against a model record of a report (two seeds): SR 50 % against
    the seeds' 75 % and 100 %, so B − A is +37.5 points; B's false Done falls from 25 % to 0."""
    a = [ep(0, True, 8, 4), ep(1, False, 3, 5), ep(2, True, 10, 5), ep(3, False, 100, 7, done=False)]
    b1 = [ep(0, True, 8, 4), ep(1, True, 5, 5), ep(2, True, 10, 5), ep(3, False, 100, 7, done=False)]
    b2 = [ep(0, True, 8, 4), ep(1, True, 5, 5), ep(2, True, 10, 5), ep(3, True, 7, 7)]
    (tmp_path / "eval").mkdir()
    (tmp_path / "eval" / "test.json").write_text(json.dumps({"episodes": [r.to_dict() for r in a]}))
    report = {"models": [model_record("savn", [b1, b2]), model_record("random", [a])]}
    (tmp_path / "table1.json").write_text(json.dumps(report))
    assert main(["compare", str(tmp_path / "eval" / "test.json"), f"{tmp_path / 'table1.json'}:savn"]) == 0
    out = capsys.readouterr().out
    cells = {
        row[0].strip(): row[1:] for row in (line.strip("| \n").split(" | ") for line in out.splitlines())
    }
    assert cells["metric"] == ["A: " + tmp_path.name, "B: savn", "B − A"]  # the run folder names A
    sr_a, sr_b, sr_diff = cells["SR"]
    assert sr_a.startswith("50.0 [") and sr_b.startswith("87.5 ± 17.7 [") and sr_diff.startswith("+37.5 [")
    false_a, false_b, false_diff = cells["false Done"]
    assert (
        false_a.startswith("25.0 [") and false_b.startswith("0.0 ± 0.0") and false_diff.startswith("-25.0 [")
    )
    assert "same actions" not in out  # these results carry no actions


def test_compare_counts_the_episodes_in_which_both_took_the_same_actions(tmp_path, capsys):
    def acted(result: EpisodeResult, actions: tuple[int, ...]) -> EpisodeResult:
        return dataclasses.replace(result, actions=actions)

    a = [
        acted(ep(0, True, 2, 2), (0, 5)),
        acted(ep(1, False, 3, 2), (0, 1, 5)),
        acted(ep(2, True, 1, 1), (5,)),
    ]
    b = [
        acted(ep(0, True, 2, 2), (0, 5)),
        acted(ep(1, True, 3, 2), (0, 2, 5)),
        acted(ep(2, True, 1, 1), (5,)),
    ]
    for name, results in (("a", a), ("b", b)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"episodes": [r.to_dict() for r in results]}))
    assert main(["compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    assert "A and B took exactly the same actions in 2 of 3 episodes (66.7 %)." in capsys.readouterr().out


@pytest.mark.parametrize(
    ("content", "b", "message"),
    [
        ('{"models": [{"model": "a3c", "episodes": [[]]}]}', "{report}", "name one of its models"),
        ("[1, 2]", "{a}", "not a mapless result file"),
        ("{not json", "{a}", "cannot read results"),
        ('{"episodes": [{"index": 0}]}', "{a}", "malformed episode record"),
        ("VAL", "{a}", "same episodes"),
    ],
)
def test_compare_refuses_what_it_cannot_pair(tmp_path, capsys, content, b, message):
    a = tmp_path / "a.json"
    a.write_text(json.dumps({"episodes": [ep(0, True, 8, 4).to_dict(), ep(1, False, 3, 5).to_dict()]}))
    other = tmp_path / "report.json"
    other.write_text(json.dumps({"episodes": [ep(5, True, 8, 4).to_dict()]}) if content == "VAL" else content)
    b_spec = str(other) if b == "{a}" else f"{other}:cvmeta"
    assert main(["compare", str(a), b_spec]) == 2
    assert message in capsys.readouterr().err


def test_a_metric_declared_once_reaches_every_report(monkeypatch):
    """One declaration (a Done rate over the L>=5 bucket, a secondary column, compared) is all that
    aggregates, seed estimates, the secondary table, differences and ``mapless compare`` read."""
    metric = Metric("l5_done_rate", "Done L≥5", "done", l5_only=True, table="details", compared=True)
    monkeypatch.setitem(METRICS, metric.name, metric)
    a = [ep(0, True, 8, 4), ep(1, False, 30, 5, done=False), ep(2, True, 10, 6), ep(3, False, 9, 7)]
    b = [dataclasses.replace(r, called_done=True) for r in a]
    assert aggregate(a)["l5_done_rate"] == pytest.approx(2 / 3)  # episodes 1-3 are L>=5; 2 and 3 Done
    assert seed_estimates([a])["l5_done_rate"].episodes == 3
    assert difference_estimates([a], [b], ["l5_done_rate"])["l5_done_rate"].mean == pytest.approx(1 / 3)
    record = model_record("x", [a])
    assert record["estimates"]["l5_done_rate"]["mean"] == pytest.approx(2 / 3)
    header, _, row = details_table([record]).splitlines()
    assert header.endswith("| Done L≥5 |") and row.endswith("| 66.7 |")
    assert "| Done L≥5 | 66.7 [" in comparison_table("a", [a], "b", [b])
    # Where it is not declared compared, the comparison leaves it out.
    monkeypatch.setitem(METRICS, metric.name, dataclasses.replace(metric, compared=False))
    assert "Done L≥5" not in comparison_table("a", [a], "b", [b])


def test_metric_declarations_are_checked():
    with pytest.raises(ValueError, match="declared twice"):
        register(Metric("success", "SR", "success"))
    # A ratio of sums (failed actions / all actions) is not a mean over episodes: no bootstrap.
    with pytest.raises(ValueError, match="ratio of sums"):
        Metric("x", "x", "failed_actions", per="ep_length")
    with pytest.raises(ValueError, match="needs an interval"):
        Metric("x", "x", "reward", interval=False, compared=True)
    with pytest.raises(ValueError, match="no bootstrap interval"):
        difference_estimates([[ep(0, True, 4, 4)]], [[ep(0, True, 4, 4)]], ["failed_action_rate"])
    # The tables' column groups and what compare shows are the declarations' (in declaration order).
    assert main_metrics() == ("success", "spl", "l5_success", "l5_spl")
    assert compared_metrics() == (
        *main_metrics(),
        "false_done_rate",
        "seen_rate",
        "short_done_rate",
        "approach_steps",
        "stops_passed",
    )
    assert [METRICS[k].scale for k in ("success", "ep_length")] == [100.0, 1.0]


def test_docs_define_every_declared_metric():
    table = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "evaluation.md").read_text()
    for name in METRICS:
        assert f"`{name}`" in table, name
