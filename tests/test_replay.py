"""Jobs the tracking store missed are replayed without anyone asking (``experiment.replay``): at the
next launch, and at the end of a sweep while a server comes back; replayed runs have their parent,
their ``worker.*`` tags and their round images, which jobs keep in their folder and the tracker takes
from there whenever MLflow did not receive them live. A real server's outage: tests/test_tracking_server.py."""

import json
import re
import pytest

from pipeline.experiment.layout import SweepFolder
from pipeline.experiment.records import RecordsFile
from pipeline.experiment.replay import RETRY_EVERY_S, replay_until_taken
from pipeline.experiment.sweep import run_sweep
from tests.test_experiment import TINY, composed

SWEEP = ["experiment=debug", *TINY, "method=[random,gopre]", "executor=local", "job.round_images=1"]


def mlflow_runs(out):
    from mlflow import MlflowClient
    client = MlflowClient(f"sqlite:///{out / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("debug")
    runs = client.search_runs([experiment.experiment_id], "") if experiment else []
    return client, [r for r in runs if r.data.tags.get("config_hash")], [r for r in runs if r.data.tags.get("kind") == "sweep"]


def image_steps(client, run) -> dict[str, list[int]]:
    """MLflow's image series of a run: key -> the steps (views) it has."""
    artifacts = [a.path for a in client.list_artifacts(run.info.run_id, "images")]
    steps: dict[str, list[int]] = {}
    for path in artifacts:  # images/<key>+step+<step>+timestamp+<ms>+<uuid>.png (MLflow's log_image layout)
        found = re.fullmatch(r"(.+)\+step\+(\d+)\+timestamp\+.*(?<!compressed)\.png", path.rsplit("/", 1)[-1])
        if found:
            steps.setdefault(found[1], []).append(int(found[2]))
    return {k: sorted(v) for k, v in steps.items()}


def assert_every_saved_round_imaged(client, out, runs) -> None:
    """Each run has, in every image series, exactly the rounds its job saved in its folder."""
    for run in runs:
        saved = SweepFolder(out).job(run.data.tags["config_hash"]).saved_round_images()
        steps = image_steps(client, run)
        assert saved and steps and all(v == sorted(saved) for v in steps.values()), (steps, sorted(saved))


def test_every_round_keeps_its_images_in_the_job_folder(tmp_path):
    out = tmp_path / "s"
    summary = run_sweep(composed([*SWEEP, "tracking=mlflow", f"output_dir={out}"]))
    assert summary.finished == 2
    for folder in SweepFolder(out).job_folders():
        result = json.loads(folder.result_file.read_text())
        picking_rounds = [r["num_views"] for r in result["rounds"] if r["selected"]]
        saved = folder.saved_round_images()
        assert sorted(saved) == picking_rounds  # each round that picked a view
        for files in saved.values():
            assert "picked" in files and any(k.startswith("render_test_") for k in files)
            assert any(k.startswith("variance_test_") for k in files)
            assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in files.values())


def test_a_launch_replays_the_finished_jobs_the_store_does_not_have_with_parent_tags_and_images(tmp_path, monkeypatch,
                                                                                             capsys):
    from pipeline.experiment import tracking
    out = tmp_path / "s"

    def away(*args, **kwargs):  # the store takes the rounds, then goes away before each job's end
        raise ConnectionError("tracking server unreachable")
    with monkeypatch.context() as patch:
        patch.setattr(tracking.MlflowTracker, "_complete", away)
        first = run_sweep(composed([*SWEEP, "tracking=mlflow", "tracking.replay_wait_s=0", f"output_dir={out}"]))
    assert first.finished == 2 and len(first.untracked) == 2
    said = capsys.readouterr()
    assert "the next launch of the same command replays them" in said.out + said.err
    again = run_sweep(composed([*SWEEP, "tracking=mlflow", f"output_dir={out}"]))
    said = capsys.readouterr()
    assert again.finished == 0  # nothing ran again
    assert "2 finished job(s) were not in" in said.out + said.err and "2 run(s) replayed" in said.out + said.err
    client, every, parents = mlflow_runs(out)
    runs = [r for r in every if r.info.status == "FINISHED"]
    assert len(runs) == 2 and {r.info.status for r in every} == {"FINISHED", "KILLED"}  # nothing left RUNNING
    relaunch = [p for p in parents if p.data.tags["jobs"] == "0"]  # the launch that replayed them
    assert len(relaunch) == 1 and {r.data.tags["mlflow.parentRunId"] for r in runs} == {relaunch[0].info.run_id}
    records = RecordsFile(out).frame.query("kind == 'final'").set_index("config_hash")
    for run in runs:
        row = records.loc[run.data.tags["config_hash"]]
        assert run.data.tags["worker.host"] == row["host"] and run.data.tags["worker.cpu"] == row["cpu"]
        assert run.data.tags["worker.code_version"] == row["worker_code_version"]
        assert records.loc[run.data.tags["config_hash"], "run_id"] == run.info.run_id  # the records name it
    assert_every_saved_round_imaged(client, out, runs)
    capsys.readouterr()
    third = run_sweep(composed([*SWEEP, "tracking=mlflow", f"output_dir={out}"]))
    assert third.finished == 0 and "were not in" not in "".join(capsys.readouterr())  # nothing left to replay


def test_images_the_progress_channel_lost_are_taken_from_the_job_folder(tmp_path, monkeypatch, capsys):
    from pipeline.experiment import tracking
    original = tracking.MlflowTracker.log_round

    def lossy(self, job, message):  # the round messages arrive, their images do not (a lost actor)
        message.images = {}
        return original(self, job, message)
    monkeypatch.setattr(tracking.MlflowTracker, "log_round", lossy)
    out = tmp_path / "s"
    summary = run_sweep(composed([*SWEEP, "tracking=mlflow", f"output_dir={out}"]))
    assert summary.finished == 2
    said = capsys.readouterr()
    assert said.out.count("taken from its job folder") + said.err.count("taken from its job folder") == 2
    client, runs, _ = mlflow_runs(out)
    assert_every_saved_round_imaged(client, out, runs)


def test_a_run_replayed_within_the_sweep_has_the_images_its_lost_run_received(tmp_path, monkeypatch):
    """The server takes a job's rounds and images live, then refuses its end; the sweep's own replay
    makes a new run, which must get every round's images from the job folder (they went to the lost
    run, ended KILLED). Found 2026-12-08: the tracker counted the lost run's images as the new run's,
    and a replayed run came without the rounds imaged before an outage (tests/test_tracking_server.py
    saw it whenever the images beat the outage)."""
    from pipeline.experiment import tracking
    original = tracking.MlflowTracker._complete
    refused = set()

    def away_once(self, run_id, logged, job, outcome, live):
        if job.config_hash not in refused:  # the first end of each job: the server is away
            refused.add(job.config_hash)
            raise ConnectionError("tracking server unreachable")
        return original(self, run_id, logged, job, outcome, live)
    monkeypatch.setattr(tracking.MlflowTracker, "_complete", away_once)
    out = tmp_path / "s"
    summary = run_sweep(composed([*SWEEP, "tracking=mlflow", "tracking.replay_wait_s=30", f"output_dir={out}"]))
    assert summary.finished == 2 and summary.untracked == [] and len(refused) == 2
    client, every, _ = mlflow_runs(out)
    replayed = [r for r in every if r.info.status == "FINISHED"]
    assert len(replayed) == 2 and sorted(r.info.status for r in every) == ["FINISHED", "FINISHED", "KILLED", "KILLED"]
    assert_every_saved_round_imaged(client, out, replayed)


class Flaky:
    """A tracker whose server answers only from the ``answers_from``-th question on."""

    uri = "http://tracking:5000"

    def __init__(self, answers_from: int):
        self.asked, self.answers_from, self.logged, self.orphans_closed = 0, answers_from, [], 0

    def answers(self):
        self.asked += 1
        return self.asked >= self.answers_from

    def close_orphans(self):
        self.orphans_closed += 1

    def log_job(self, job, outcome):
        self.logged.append(job.config_hash)
        return f"run-{job.config_hash}"


@pytest.fixture(scope="module")
def finished_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay") / "s"
    run_sweep(composed([*SWEEP, "tracking=none", f"output_dir={out}"]))
    jobs = {j.config_hash: j for j in SweepFolder(out).read_jobs()}
    return out, jobs


def test_the_end_of_a_sweep_retries_while_the_server_is_away_and_stops_at_the_limit(finished_sweep):
    out, jobs = finished_sweep
    lines, slept = [], []
    tracker = Flaky(answers_from=4)  # away for three tries
    done = replay_until_taken(tracker, jobs, out, RecordsFile(out), list(jobs), 120.0, lines.append, slept.append)
    assert sorted(done.replayed) == sorted(jobs) and not done.failed and sorted(tracker.logged) == sorted(jobs)
    assert slept == [RETRY_EVERY_S] * 3 and tracker.orphans_closed == 1
    assert len(lines) == 1 and "trying again every 10 s for up to 120 s" in lines[0]
    assert RecordsFile(out).frame.query("kind == 'final'")["run_id"].str.startswith("run-").all()
    tracker = Flaky(answers_from=100)  # never back within the limit: nothing replayed, all left
    done = replay_until_taken(tracker, jobs, out, RecordsFile(out), list(jobs), 35.0, lines.append,
                              lambda s: None)
    assert sorted(done.failed) == sorted(jobs) and not done.replayed and tracker.logged == []


def test_a_job_the_store_refuses_is_left_for_the_next_try_and_the_others_go_on(finished_sweep):
    out, jobs = finished_sweep
    first, second = sorted(jobs)

    class Refuses(Flaky):
        def log_job(self, job, outcome):
            if job.config_hash == first and self.asked < 2:
                raise ConnectionError("server gone")
            return super().log_job(job, outcome)
    tracker = Refuses(answers_from=1)
    done = replay_until_taken(tracker, jobs, out, RecordsFile(out), [first, second], 60.0, lambda _: None,
                              lambda s: None)
    assert done.replayed == [second, first] and tracker.logged == [second, first]
    unknown = replay_until_taken(Flaky(1), {}, out, RecordsFile(out), [first], 0.0, lambda _: None)
    assert unknown.unknown == [first] and "not replayable" in unknown.line()



def test_an_executor_that_refuses_to_run_leaves_no_mlflow_run_running(tmp_path, monkeypatch):
    from pipeline.experiment.episode_settings import ConfigError
    from pipeline.experiment.executors.local import LocalExecutor

    def refuse(self, jobs, scenes, on_done, on_round=None):  # as a node probe that names a node does
        raise ConfigError("executor: node n1 cannot read /data")
    monkeypatch.setattr(LocalExecutor, "map", refuse)
    out = tmp_path / "s"
    with pytest.raises(ConfigError, match="node n1"):
        run_sweep(composed([*SWEEP, "tracking=mlflow", f"output_dir={out}"]))
    _, runs, parents = mlflow_runs(out)
    assert [p.info.status for p in parents] == ["FAILED"] and runs == []
