"""``graphslam config show [--track]``: the default configuration, commented, as a file to edit and
pass back with ``--config`` (what ``configs/default.yaml`` and ``configs/track.yaml`` hold in the
repository, available wherever graphslam is installed)."""

from __future__ import annotations

import typer

from graphslam.cli.base import Typer, app

config_app = Typer(rich_markup_mode=None, help="The configuration files: the defaults, commented, to edit and pass with --config.")
app.add_typer(config_app, name="config")


@config_app.command("show")
def show(
    track: bool = typer.Option(False, "--track", help="The tracking configuration (track --config) instead of the survey's."),
) -> None:
    """Print the default survey configuration (survey, survey-batch, bench real --config) as YAML with
    each field's meaning; --track: track's. A partial file is merged over the defaults, e.g.
    `graphslam config show > survey.yaml`, edit, then `graphslam survey ... --config survey.yaml`."""
    if track:
        from graphslam.tracking_config import commented_track_yaml

        typer.echo(commented_track_yaml(), nl=False)
    else:
        from graphslam.config import commented_yaml

        typer.echo(commented_yaml(), nl=False)
