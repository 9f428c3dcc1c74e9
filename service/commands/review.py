"""``lanemap review``: accept and reject a map's detections by their score, as one changeset."""

from __future__ import annotations

import typer

from mapbuilder.store import Store

from ..cli_errors import fail
from ..cli_io import bbox_option


def register(app: typer.Typer) -> None:
    @app.command("review")
    def review(
        map_id: str = typer.Argument(..., metavar="MAP"),
        accept_from: float = typer.Option(None, "--accept-from", min=0.0, max=1.0, metavar="SCORE",
                                          help="Accept the unreviewed detections scoring at least SCORE."),
        reject_below: float = typer.Option(None, "--reject-below", min=0.0, max=1.0, metavar="SCORE",
                                           help="Reject the unreviewed detections scoring below SCORE."),
        bbox: str = typer.Option(None, "--bbox", metavar="MINLON,MINLAT,MAXLON,MAXLAT",
                                 help="Only inside this box (WGS84 minLon,minLat,maxLon,maxLat)."),
        comment: str = typer.Option("", "--comment", help="Comment for the edit log."),
        dry_run: bool = typer.Option(False, "--dry-run", help="Say what it would do; change nothing."),
    ) -> None:
        """Accept and reject a map's unreviewed detections by their score, as one changeset.

        What a team does before reviewing the doubtful detections one by one
        (the editor's review queue). The changeset is in the history and a
        revert undoes it; detections without a score and markings a person
        decided on are left as they are. 'lanemap maps summary MAP' shows how
        the unreviewed scores spread.
        """
        if accept_from is None and reject_below is None:
            fail("give --accept-from SCORE, --reject-below SCORE or both")
        if accept_from is not None and reject_below is not None and reject_below > accept_from:
            fail(f"--reject-below {reject_below:g} is above --accept-from {accept_from:g}")
        res = Store().review_by_score(map_id, accept_from=accept_from, reject_below=reject_below,
                                      lonlat_box=bbox_option(bbox),
                                      who="cli", comment=comment, dry_run=dry_run)  # fmt: skip
        what = f"{res.accepted:,} detections accepted and {res.rejected:,} rejected"
        if dry_run:
            typer.echo(f"map {map_id}: would have {what}; nothing changed (--dry-run)")
        elif res.changeset_id is None:
            typer.echo(f"map {map_id}: no unreviewed detection with a score is in that range; nothing changed")
        else:
            typer.echo(f"map {map_id}: {what} in changeset {res.changeset_id} (revision {res.revision})")
