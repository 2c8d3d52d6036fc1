"""`python -m cvslam_cli` and the `cvslam` console script. A Ctrl-C while the command line is
still loading (its imports take a while) ends like one later: exit 130, one line."""

import sys


def main() -> None:
    try:
        from cvslam_cli.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("cvslam: interrupted\n")
        sys.exit(130)
    cli_main()


if __name__ == "__main__":
    main()
