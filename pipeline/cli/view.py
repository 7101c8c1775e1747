"""``gopre-view``: open an episode in the web 3D viewer.

    gopre-view outputs/demo/jobs/<config hash>              # http://127.0.0.1:8080
    gopre-view RUN_ID --mlflow-uri sqlite:///outputs/demo/mlflow.db --port 8090
    gopre-view outputs/demo/jobs/<hash> --host 0.0.0.0       # reachable from other machines
    gopre-view outputs/demo                                  # a sweep folder: lists its jobs
    gopre-view copied/jobs/<hash> --data-root /data          # a sweep copied from another machine

SOURCE: a job folder (finished, or running: the rounds so far) or an MLflow run id of a job
with ``--mlflow-uri`` (its output_dir/config_hash tags name the job folder, which must be here).
Serves on loopback unless ``--host`` says otherwise; prints the address; Ctrl-C stops it.
Exit status 0, or 1 with one line naming the source and the reason.
"""

from __future__ import annotations

import argparse
import sys
import time

from pipeline.cli import alias_note, command_name


def start(source: str, mlflow_uri: str | None = None, host: str = "127.0.0.1", port: int = 8080,
          start_round: int | None = None, scene: str | None = None, data_root: str | None = None,
          per_client: bool = False):
    """Load the run and serve it; returns (viser server, viewer). Raises ValueError.

    ``per_client``: every browser tab gets its own viewer (its own goal, round and camera), and
    the second value is the {client id: EpisodeViewer} of the tabs connected so far; else one
    viewer on the server that every tab shares (what the in-process tests drive)."""
    import viser  # the viewing edge

    from pipeline.view.run import load_run
    from pipeline.view.server import EpisodeViewer, per_client_viewers
    run = load_run(source, mlflow_uri, scene, data_root)
    if not run.rounds:
        raise ValueError(f"{run.folder}: the episode has no finished selection round to show")
    server = viser.ViserServer(host=host, port=port, label="gopre", verbose=False)
    try:
        viewer = per_client_viewers(run, server, start_round) if per_client else \
            EpisodeViewer(run, server, start_round)
    except Exception:
        server.stop()
        raise
    return server, viewer


def tcp_port(text: str) -> int:
    """``--port``: a TCP port, 1-65535 (a bad one used to leave a server thread's traceback and a
    process that never exited)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a TCP port 1-65535, got {text!r}") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port 1-65535, got {port}")
    return port


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=command_name("view"), description=__doc__,
                                     epilog=alias_note("view"),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="job folder outputs/<sweep>/jobs/<config hash>, or an MLflow run id")
    parser.add_argument("--mlflow-uri", help="tracking URI when SOURCE is an MLflow run id")
    parser.add_argument("--host", default="127.0.0.1", help="interface to serve on (default loopback)")
    parser.add_argument("--port", type=tcp_port, default=8080, help="TCP port, 1-65535 (default 8080)")
    parser.add_argument("--round", type=int, default=None, help="round shown first (default the last)")
    parser.add_argument("--scene", default=None, help="the scene folder, when not where the job ran")
    parser.add_argument("--data-root", default=None,
                        help="where the datasets are on this machine (a sweep copied from another)")
    args = parser.parse_args(argv)
    try:
        server, _viewers = start(args.source, args.mlflow_uri, args.host, args.port, args.round,
                                 args.scene, args.data_root, per_client=True)
    except (ValueError, OSError) as err:
        print(f"{command_name('view')}: {err}", file=sys.stderr)  # every error names its source
        return 1
    print(f"{command_name('view')}: {args.source} at http://{args.host}:{server.get_port()} (Ctrl-C stops; "
          "each browser tab has its own goal, round and camera)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
