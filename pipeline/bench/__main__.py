"""Dispatch ``python -m pipeline.bench {render,...} [options]``."""

import importlib
import sys

COMMANDS = {"render": "pipeline.bench.render", "fisher": "pipeline.bench.fisher",
            "select": "pipeline.bench.select", "episode": "pipeline.bench.episode",
            "train": "pipeline.bench.train"}


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
        print(f"usage: python -m pipeline.bench {{{','.join(COMMANDS)}}} [options]", file=sys.stderr)
        raise SystemExit(2)
    importlib.import_module(COMMANDS[sys.argv[1]]).main(sys.argv[2:])


if __name__ == "__main__":
    main()
