"""Where the test suite's time goes, from the lines ``GOPRE_TEST_RESOURCES=path make test`` wrote
(tests/conftest.py): the costliest tests by CPU seconds (their own and their child processes'), the
costliest modules, the chains (the tests that run one after another in one worker: "ray" and
"servers"; a log written before there were two has one, "cluster"), and the wall time the suite cannot
go below on N cores (its CPU seconds spread evenly, or the longest chain, whichever is longer). CPU
seconds hardly move with the machine's load, so a run beside a sweep still plans a diet.

    python tools/test_costs.py /tmp/costs.jsonl [--top 25] [--cores 2]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Cost:
    test: str
    wall_s: float
    cpu_s: float            # the test's own process
    children_cpu_s: float   # the processes it started and reaped
    worker: str
    chain: str | None = None  # the chain it ran in, None for none
    cluster: bool = False     # logs before 2026-12-08 flag a test of their one chain instead

    @property
    def chain_name(self) -> str | None:
        return self.chain or ("cluster" if self.cluster else None)

    @property
    def total_cpu_s(self) -> float:
        return self.cpu_s + self.children_cpu_s

    @property
    def module(self) -> str:
        return self.test.split("::", 1)[0]


def read_costs(path: Path) -> list[Cost]:
    costs = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            costs.append(Cost(**json.loads(line)))
        except (ValueError, TypeError) as err:
            raise SystemExit(f"{path}:{number}: not a line tests/conftest.py writes ({err})") from err
    return costs


def summary(costs: list[Cost], top: int, cores: int) -> str:
    total = sum(c.total_cpu_s for c in costs)
    chains: dict[str, list[Cost]] = defaultdict(list)
    for c in costs:
        if c.chain_name is not None:
            chains[c.chain_name].append(c)
    walls = {name: sum(c.wall_s for c in items) for name, items in chains.items()}
    floor = max([total / cores, *walls.values()])
    lines = [f"{len(costs)} tests, {total:,.0f} CPU s ({total / 60:.1f} min), {sum(c.wall_s for c in costs):,.0f} wall s "
             f"summed over tests"]
    for name, items in sorted(chains.items(), key=lambda kv: -walls[kv[0]]):
        lines.append(f"{name} chain: {len(items)} tests, {walls[name]:,.0f} wall s, "
                     f"{sum(c.total_cpu_s for c in items):,.0f} CPU s")
    lines += [f"the suite's floor on {cores} cores: {floor / 60:.1f} min (CPU spread evenly, or the longest chain if "
              "longer)", "", f"costliest {top} tests (CPU s: own + children, wall s):"]
    for c in sorted(costs, key=lambda c: -c.total_cpu_s)[:top]:
        chain_mark = f" [{c.chain_name}]" if c.chain_name else ""
        lines.append(f"  {c.total_cpu_s:7.1f} = {c.cpu_s:6.1f} + {c.children_cpu_s:6.1f}  {c.wall_s:7.1f}  {c.test}{chain_mark}")
    by_module: dict[str, list[Cost]] = defaultdict(list)
    for c in costs:
        by_module[c.module].append(c)
    lines += ["", f"costliest {top} modules (CPU s, tests, wall s):"]
    for module, items in sorted(by_module.items(), key=lambda kv: -sum(c.total_cpu_s for c in kv[1]))[:top]:
        lines.append(f"  {sum(c.total_cpu_s for c in items):7.1f}  {len(items):4d}  {sum(c.wall_s for c in items):7.1f}  {module}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path)
    parser.add_argument("--top", type=int, default=25)
    parser.add_argument("--cores", type=int, default=2)
    args = parser.parse_args(argv)
    print(summary(read_costs(args.log), args.top, args.cores))


if __name__ == "__main__":
    main()
