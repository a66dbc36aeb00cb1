"""Object DAGs: constructors, queries, JSON loading and every validation error."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.graphs import GraphSpecError, ObjectDAG, chain, collider, full, load_dag, random_dag

DAGS_DIR = Path(__file__).resolve().parents[2] / "envs" / "dags"


def test_named_constructors() -> None:
    assert collider(4).edges == ((0, 3), (1, 3), (2, 3))
    assert chain(4).edges == ((0, 1), (1, 2), (2, 3))
    assert full(4).edges == ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))
    assert chain(1).edges == () and full(1).num_objects == 1


def test_queries() -> None:
    dag = ObjectDAG(5, ((3, 1), (1, 0), (3, 4), (4, 0), (2, 4)))
    assert dag.parents(0) == (1, 4) and dag.parents(3) == ()
    assert dag.children(3) == (1, 4)
    assert dag.descendants(3) == {0, 1, 4} and dag.descendants(0) == frozenset()
    assert dag.ancestors(0) == {1, 2, 3, 4}
    assert dag.topological_order() == (2, 3, 1, 4, 0)  # Kahn, smallest ready index first


def test_edges_are_stored_sorted_so_equal_graphs_compare_equal() -> None:
    assert ObjectDAG(3, ((1, 2), (0, 2))) == ObjectDAG(3, [[0, 2], [1, 2]])


def test_named_specs_and_json_round_trip(tmp_path: Path) -> None:
    assert load_dag("chain", 6) == chain(6)
    dag = random_dag(7, 9, seed=3)
    path = tmp_path / "g.json"
    path.write_text(dag.to_json())
    assert load_dag(path, 99) == dag
    assert load_dag(str(path), 99) == dag


def test_json_num_objects_wins_and_is_optional(tmp_path: Path) -> None:
    path = tmp_path / "g.json"
    path.write_text(json.dumps({"num_objects": 4, "edges": [[0, 3]]}))
    assert load_dag(path, 10).num_objects == 4
    path.write_text(json.dumps({"edges": [[0, 3]]}))
    assert load_dag(path, 10).num_objects == 10


def test_shipped_random10_is_reproducible_and_not_a_named_graph() -> None:
    dag = load_dag(DAGS_DIR / "random10.json", 10)
    assert dag == random_dag(10, 14, seed=0)
    assert dag not in (collider(10), chain(10), full(10))
    assert dag.topological_order() != tuple(range(10))


@pytest.mark.parametrize(("name", "edges", "seed"), [("random5-6-1.json", 6, 1), ("random5-8-2.json", 8, 2)])
def test_shipped_five_object_dags_are_the_benchmarks_random_graphs(name: str, edges: int, seed: int) -> None:
    """The files ``causeway run --graph`` takes for ``benchmarks.fdr_graphs``' ``random:5:<edges>:<seed>``."""
    assert load_dag(DAGS_DIR / name, 5) == random_dag(5, edges, seed=seed)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ({"num_objects": 3}, "missing key 'edges'"),
        ([[0, 1]], "must be a JSON object"),
        ({"edges": [[0, 1]], "edge": []}, "unknown keys ['edge']"),
        ({"edges": {"0": 1}}, "'edges' must be a list"),
        ({"edges": [[0, 1, 2]]}, "must be a [parent, child] pair"),
        ({"edges": [[0, 1.0]]}, "non-int object id"),
        ({"edges": [["0", 1]]}, "non-int object id"),
        ({"edges": [[True, 1]]}, "non-int object id"),
        ({"num_objects": 3, "edges": [[0, 3]]}, "object id 3 out of range [0, 2]"),
        ({"num_objects": 3, "edges": [[-1, 2]]}, "object id -1 out of range"),
        ({"edges": [[1, 1]]}, "self-loop"),
        ({"edges": [[0, 1], [0, 1]]}, "duplicate edge [0, 1]"),
        ({"edges": [[0, 1], [1, 2], [2, 0]]}, "cycle: 0 -> 1 -> 2 -> 0"),
        ({"num_objects": 0, "edges": []}, "num_objects must be >= 1, got 0"),
        ({"num_objects": "3", "edges": []}, "num_objects must be an int"),
    ],
)
def test_invalid_json_graphs_name_the_problem_and_the_file(tmp_path: Path, content: object, message: str) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(content))
    with pytest.raises(GraphSpecError) as err:
        load_dag(path, 3)
    assert message in str(err.value) and str(path) in str(err.value)


def test_missing_file_and_invalid_json_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(GraphSpecError, match="graph file not found: .*nope.json .*collider, chain, full"):
        load_dag(tmp_path / "nope.json", 3)
    path = tmp_path / "broken.json"
    path.write_text('{"edges": [[0, 1]')
    with pytest.raises(GraphSpecError, match=f"invalid JSON in graph file {path}"):
        load_dag(path, 3)


def test_cycle_message_names_a_real_cycle() -> None:
    with pytest.raises(GraphSpecError, match=r"cycle: 2 -> 3 -> 4 -> 2"):
        ObjectDAG(5, ((0, 2), (2, 3), (3, 4), (4, 2)))


@pytest.mark.parametrize("make", [collider, chain, full])
def test_constructors_reject_bad_sizes(make: object) -> None:
    with pytest.raises(GraphSpecError, match="num_objects must be >= 1"):
        make(0)  # type: ignore[operator]


def test_graph_spec_error_is_a_value_error() -> None:
    assert issubclass(GraphSpecError, ValueError)
    with pytest.raises(GraphSpecError, match="num_edges must be in"):
        random_dag(4, 7, seed=0)


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 9), density=st.floats(0, 1), seed=st.integers(0, 2**32 - 1))
def test_random_dags_are_consistent(n: int, density: float, seed: int) -> None:
    dag = random_dag(n, round(density * n * (n - 1) / 2), seed)
    position = {k: i for i, k in enumerate(dag.topological_order())}
    assert sorted(position) == list(range(n))
    assert all(position[p] < position[c] for p, c in dag.edges)
    for k in range(n):
        assert all(k in dag.ancestors(d) for d in dag.descendants(k))
        assert set(dag.parents(k)) <= dag.ancestors(k)
    assert ObjectDAG(n, dag.edges) == dag
