"""Energy records: the JSON-lines contract between `ebvla-eval` and the monitoring tools."""

import dataclasses
import gzip
import json
import math
from dataclasses import asdict

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring import records as records_module
from lerobot_policy_ebvla.monitoring.records import (
    COMPRESSED_RECORDS_FILENAME,
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    compress_records,
    features_path,
    group_by_episode,
    load_episodes,
    read_energy_records,
    record_from_json,
    record_to_json,
    resolve_record_files,
    write_energy_records,
)


def record(
    episode=0, chunk=0, final=1.0, initial=2.0, success=True, task="t", perturbation="none", severity=0.0
):
    return EnergyRecord(
        episode_index=episode,
        chunk_index=chunk,
        env_step=8 * chunk,
        initial_energy=initial,
        final_energy=final,
        success=success,
        task=task,
        seed=1000 + episode,
        perturbation=perturbation,
        severity=severity,
    )


def test_records_round_trip(tmp_path):
    records = [record(chunk=0), record(chunk=1, perturbation="camera", severity=0.5)]
    records.append(EnergyRecord(1, 0, 0, 3.0, 1.5, False, "t", None, "none", 0.0))
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, records)
    assert read_energy_records(path) == records


def test_mcmc_chains_round_trip_and_old_rows_read_without_them(tmp_path):
    records = [dataclasses.replace(record(chunk=0), mcmc_chains=4), record(chunk=1)]
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, records)
    assert "mcmc_chains" not in path.read_text().splitlines()[1]
    assert [r.mcmc_chains for r in read_energy_records(path)] == [4, None]


def test_context_energy_round_trips_and_old_rows_read_without_it(tmp_path):
    records = [dataclasses.replace(record(chunk=0), context_energy=-0.25), record(chunk=1)]
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, records)
    assert "context_energy" not in path.read_text().splitlines()[1]
    assert [r.context_energy for r in read_energy_records(path)] == [-0.25, None]
    with pytest.raises(ValueError, match="context_energy"):
        record_from_json({**json.loads(record_to_json(records[0])), "context_energy": "high"}, "row 1")


def test_restart_spread_and_context_features_round_trip(tmp_path):
    records = [
        dataclasses.replace(
            record(chunk=i), restart_spread=0.1 * i, context_feature=np.full(3, i, np.float32)
        )
        for i in range(2)
    ]
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, records)
    assert features_path(path).name == "energy_records.features.npy"
    read = read_energy_records(path)
    assert [r.restart_spread for r in read] == [0.0, 0.1]
    np.testing.assert_array_equal(np.stack([r.context_feature for r in read]), [[0, 0, 0], [1, 1, 1]])


def test_rows_without_the_baseline_fields_still_read(tmp_path):
    row = {k: v for k, v in asdict(record()).items() if k not in ("restart_spread", "context_feature")}
    (tmp_path / "r.jsonl").write_text(json.dumps(row) + "\n")
    (read,) = read_energy_records(tmp_path / "r.jsonl")
    assert read.restart_spread is None and read.context_feature is None


def test_features_must_cover_every_record_or_none(tmp_path):
    records = [dataclasses.replace(record(), context_feature=np.zeros(2)), record(chunk=1)]
    with pytest.raises(ValueError, match="context_feature"):
        write_energy_records(tmp_path / "r.jsonl", records)


def test_rewriting_records_without_features_removes_stale_features(tmp_path):
    path = write_energy_records(
        tmp_path / "r.jsonl", [dataclasses.replace(record(), context_feature=np.zeros(2))]
    )
    write_energy_records(path, [record()], overwrite=True)
    assert not features_path(path).exists() and read_energy_records(path)[0].context_feature is None


def test_features_of_another_length_are_rejected(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record(), record(chunk=1)])
    np.save(features_path(path), np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match="one row per record"):
        read_energy_records(path)


def test_infinite_energy_is_written_as_a_string_and_read_back_as_inf(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record(final=math.inf, initial=-math.inf)])
    row = json.loads(path.read_text())
    assert row["final_energy"] == "inf" and row["initial_energy"] == "-inf"
    (loaded,) = read_energy_records(path)
    assert loaded.final_energy == math.inf and loaded.initial_energy == -math.inf


def test_nan_energy_round_trips(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record(final=math.nan)])
    assert math.isnan(read_energy_records(path)[0].final_energy)


def test_python_json_infinity_token_is_accepted(tmp_path):
    row = asdict(record())
    row["final_energy"] = math.inf
    path = tmp_path / "r.jsonl"
    path.write_text(json.dumps(row) + "\n")  # writes the bare token `Infinity`
    assert read_energy_records(path)[0].final_energy == math.inf


def test_write_refuses_to_overwrite_an_existing_file(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record()])
    with pytest.raises(FileExistsError):
        write_energy_records(path, [record(final=9.0)])
    assert read_energy_records(path)[0].final_energy == 1.0


def test_write_overwrites_when_asked(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record()])
    write_energy_records(path, [record(final=9.0)], overwrite=True)
    assert read_energy_records(path)[0].final_energy == 9.0


def test_write_leaves_no_temporary_file(tmp_path):
    write_energy_records(tmp_path / "r.jsonl", [record()])
    assert [p.name for p in tmp_path.iterdir()] == ["r.jsonl"]


def test_failed_write_keeps_the_previous_file(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record()])

    def broken_records():
        yield record(final=9.0)
        raise RuntimeError("evaluation crashed")

    with pytest.raises(RuntimeError):
        write_energy_records(path, broken_records(), overwrite=True)
    assert read_energy_records(path)[0].final_energy == 1.0
    assert len(list(tmp_path.iterdir())) == 1


def test_read_accepts_the_eval_folder(tmp_path):
    write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, [record()])
    assert len(read_energy_records(tmp_path)) == 1


def test_read_error_names_line_and_missing_field(tmp_path):
    path = write_energy_records(tmp_path / "r.jsonl", [record(), record(chunk=1)])
    lines = path.read_text().splitlines()
    row = json.loads(lines[1])
    del row["final_energy"]
    path.write_text(lines[0] + "\n" + json.dumps(row) + "\n")
    with pytest.raises(ValueError, match=r"r\.jsonl:2: missing field\(s\) `final_energy`"):
        read_energy_records(path)


def test_read_error_names_a_malformed_field(tmp_path):
    row = asdict(record())
    row["chunk_index"] = "3"
    (tmp_path / "r.jsonl").write_text(json.dumps(row) + "\n")
    with pytest.raises(ValueError, match=r"r\.jsonl:1: field `chunk_index` must be an integer"):
        read_energy_records(tmp_path / "r.jsonl")


def test_read_error_names_a_line_that_is_not_json(tmp_path):
    (tmp_path / "r.jsonl").write_text("{not json\n")
    with pytest.raises(ValueError, match=r"r\.jsonl:1: invalid JSON"):
        read_energy_records(tmp_path / "r.jsonl")


def test_group_by_episode_sorts_chunks(tmp_path):
    episodes = group_by_episode([record(chunk=2), record(chunk=0), record(chunk=1)])
    (chunks,) = episodes.values()
    assert [r.chunk_index for r in chunks] == [0, 1, 2]


def test_group_by_episode_separates_tasks_with_the_same_episode_index():
    episodes = group_by_episode([record(task="a"), record(task="b"), record(task="a", chunk=1)])
    assert [len(chunks) for chunks in episodes.values()] == [2, 1]


def test_group_by_episode_rejects_duplicate_chunks():
    with pytest.raises(ValueError, match="duplicate chunk indices"):
        group_by_episode([record(chunk=0), record(chunk=0)])


def test_record_paths_accept_files_folders_and_glob_patterns(tmp_path):
    for name in ("pose1", "pose2"):
        write_energy_records(tmp_path / name / ENERGY_RECORDS_FILENAME, [record()])
    files = resolve_record_files([str(tmp_path / "pose*"), tmp_path / "pose1" / ENERGY_RECORDS_FILENAME])
    assert [f.parent.name for f in files] == ["pose1", "pose2"]


def test_record_paths_that_match_nothing_are_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="energy_records.jsonl"):
        resolve_record_files([str(tmp_path / "missing*")])


def test_load_episodes_keeps_same_index_episodes_of_different_files_apart(tmp_path):
    for name in ("a", "b"):
        write_energy_records(tmp_path / name / ENERGY_RECORDS_FILENAME, [record(), record(chunk=1)])
    assert len(load_episodes([tmp_path / "a", tmp_path / "b"])) == 2


def test_held_flag_round_trips_and_a_non_boolean_is_rejected(tmp_path):
    path = tmp_path / "records.jsonl"
    records = [
        dataclasses.replace(record(chunk=0), held=True),
        dataclasses.replace(record(chunk=1), held=False),
        record(chunk=2),
    ]
    write_energy_records(path, records)
    assert [r.held for r in read_energy_records(path)] == [True, False, None]
    with pytest.raises(ValueError, match="`held`"):
        record_from_json({**json.loads(record_to_json(record())), "held": "yes"})


# Compressed records, to commit.


def with_features(records):
    return [dataclasses.replace(r, context_feature=np.full(3, i, np.float32)) for i, r in enumerate(records)]


def test_compressed_records_round_trip(tmp_path):
    records = [record(chunk=0), record(chunk=1, final=math.inf), record(episode=1, success=False)]
    path = write_energy_records(tmp_path / COMPRESSED_RECORDS_FILENAME, records)
    assert json.loads(gzip.decompress(path.read_bytes()).splitlines()[1])["final_energy"] == "inf"
    assert read_energy_records(path) == records


def test_compressed_records_keep_their_features_compressed_beside_them(tmp_path):
    path = write_energy_records(
        tmp_path / COMPRESSED_RECORDS_FILENAME, with_features([record(), record(chunk=1)])
    )
    assert features_path(path).name == "energy_records.features.npy.gz"
    read = read_energy_records(path)
    np.testing.assert_array_equal(np.stack([r.context_feature for r in read]), [[0, 0, 0], [1, 1, 1]])


def test_compressed_records_with_uncompressed_features_beside_them_still_read(tmp_path):
    path = write_energy_records(
        tmp_path / ENERGY_RECORDS_FILENAME, with_features([record(), record(chunk=1)])
    )
    (tmp_path / COMPRESSED_RECORDS_FILENAME).write_bytes(gzip.compress(path.read_bytes()))
    path.unlink()
    read = read_energy_records(tmp_path)
    assert read[1].context_feature.tolist() == [1, 1, 1]


def test_a_folder_of_compressed_records_is_found_by_every_reader(tmp_path):
    write_energy_records(tmp_path / "run" / COMPRESSED_RECORDS_FILENAME, [record(), record(chunk=1)])
    assert [f.name for f in resolve_record_files([tmp_path / "ru*"])] == [COMPRESSED_RECORDS_FILENAME]
    assert len(read_energy_records(tmp_path / "run")) == 2
    assert len(load_episodes([tmp_path / "run"])) == 1


def test_a_folder_holding_both_forms_is_refused(tmp_path):
    write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, [record()])
    write_energy_records(tmp_path / COMPRESSED_RECORDS_FILENAME, [record()])
    with pytest.raises(ValueError, match="holds both"):
        resolve_record_files([tmp_path])


def test_compress_records_replaces_every_records_file_below_a_folder(tmp_path):
    runs = {name: with_features([record(chunk=0), record(chunk=1, final=math.nan)]) for name in ("a", "b/c")}
    for name, records in runs.items():
        write_energy_records(tmp_path / name / ENERGY_RECORDS_FILENAME, records)
    written = compress_records([tmp_path])
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*.*")) == [
        "a/energy_records.features.npy.gz",
        "a/energy_records.jsonl.gz",
        "b/c/energy_records.features.npy.gz",
        "b/c/energy_records.jsonl.gz",
    ]
    assert len(written) == 2
    read = read_energy_records(tmp_path / "b" / "c")
    assert read[0] == runs["b/c"][0] and math.isnan(read[1].final_energy)
    assert read[1].context_feature.tolist() == [1, 1, 1]


def test_compressing_the_same_records_twice_gives_the_same_bytes(tmp_path):
    for name in ("a", "b"):
        write_energy_records(
            tmp_path / name / ENERGY_RECORDS_FILENAME, with_features([record(), record(chunk=1)])
        )
    compress_records([tmp_path / "a", tmp_path / "b"])
    for suffix in ("jsonl.gz", "features.npy.gz"):
        assert (tmp_path / "a" / f"energy_records.{suffix}").read_bytes() == (
            tmp_path / "b" / f"energy_records.{suffix}"
        ).read_bytes()


def test_compress_records_can_keep_the_originals(tmp_path):
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, [record()])
    compress_records([path], keep_original=True)
    assert path.exists() and (tmp_path / COMPRESSED_RECORDS_FILENAME).exists()


def test_compress_records_of_a_folder_without_records_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match=ENERGY_RECORDS_FILENAME):
        compress_records([tmp_path])


def test_compress_records_runs_as_a_module_command(tmp_path, capsys):
    write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, [record()])
    records_module.main([f"--paths=[{tmp_path}]"])
    assert capsys.readouterr().out.strip() == str(tmp_path / COMPRESSED_RECORDS_FILENAME)
