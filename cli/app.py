"""The `ssg` command line (placeholder until the CLI lands)."""


def main() -> None:
    raise SystemExit("ssg: not implemented yet")
