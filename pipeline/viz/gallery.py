"""An HTML gallery of the figures (self-contained page, PNGs linked by relative path), kept up to date across
runs through a JSON manifest beside it.

    from pipeline.viz.gallery import GalleryEntry, write_gallery, link_gallery
    write_gallery("studies/s/gallery.html", [GalleryEntry(png="viz/a.png", section="worst", title="...")],
                  title="imtune study s", replace_sections=("worst", "best", "random"), scope="<config hash>")
    link_gallery("studies/s/report.html", "gallery.html")   # adds a link to an existing report (idempotent)

``gallery.json`` (beside the HTML) lists every entry. A new entry replaces an old one with the same PNG;
``replace_sections`` drops the old entries of those sections that have the same ``scope`` (a re-run of the
worst / best / random selection of a configuration replaces its previous selection, other configurations
stay); entries whose PNG no longer exists are dropped.
"""
from __future__ import annotations

import datetime as _dt
import html
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pipeline.fileio import atomic_write

MANIFEST = "gallery.json"
SECTIONS = {
    "compare": "Comparisons: the same pair, two configurations",
    "worst": "Stereo: worst pairs (largest pose error)",
    "best": "Stereo: best pairs (smallest pose error)",
    "random": "Stereo: random sample of pairs",
    "chosen": "Stereo: chosen pairs",
    "multiview": "Multiview: reconstructed bags (blue: keypoint in the 3D model, red: not)",
}
LINK_MARKER = "<!-- imtune-gallery-link -->"


@dataclass
class GalleryEntry:
    """One figure. png: path relative to the gallery HTML; section: a key of ``SECTIONS``; title: first caption
    line; lines: further caption lines; scope: groups entries of one configuration (see the module docstring);
    data: numbers kept in the manifest (JSON-able)."""
    png: str
    section: str
    title: str
    lines: list = field(default_factory=list)
    scope: str = ""
    data: dict = field(default_factory=dict)
    created: str = ""


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def read_manifest(html_path: str | Path) -> list[GalleryEntry]:
    """Entries of the gallery at ``html_path`` (empty when there is none; an unreadable manifest is ignored)."""
    return _manifest(Path(html_path).with_name(MANIFEST))[0]


def _manifest(p: Path) -> tuple[list[GalleryEntry], str | None]:
    """(entries, None) of the manifest ``p`` (none when absent); ([], why) when it is there but cannot be read."""
    if not p.exists():
        return [], None
    try:
        raw = json.loads(p.read_text())
        names = set(GalleryEntry.__dataclass_fields__)
        return [GalleryEntry(**{k: v for k, v in e.items() if k in names}) for e in raw.get("entries", [])], None
    except UnicodeDecodeError:
        return [], "not UTF-8 text"
    except ValueError as e:
        return [], f"not valid JSON: {str(e).splitlines()[0][:80]}"
    except OSError as e:
        return [], e.strerror or str(e)
    except (TypeError, AttributeError):
        return [], "not a gallery manifest (an object with a list of entries)"


def write_gallery(html_path: str | Path, entries: list[GalleryEntry], title: str = "imtune gallery",
                  replace_sections: tuple = (), scope: str | None = None, links: dict | None = None,
                  intro: str | None = None) -> Path:
    """Merge ``entries`` into the gallery at ``html_path`` (see the module docstring) and rewrite its HTML.
    links: {label: href} shown at the top (e.g. the study's report). Returns the HTML path."""
    html_path = Path(html_path)
    root = html_path.parent
    old, why = _manifest(root / MANIFEST)
    if why:  # cut short, hand-edited: kept aside, never silently replaced by this run's entries alone
        import logging
        import os
        aside = root / f"{MANIFEST}.damaged"
        try:
            os.replace(root / MANIFEST, aside)
            kept_as = f"kept as {aside}"
        except OSError as err:
            kept_as = f"left in place ({err.strerror or err})"
        logging.getLogger(__name__).warning(
            "warning: gallery manifest %s cannot be read (%s): %s; the gallery restarts from this run's figures "
            "(earlier PNGs stay in their folder)", root / MANIFEST, why, kept_as)
    new_pngs = {e.png for e in entries}
    kept = []
    for e in old:
        if e.png in new_pngs:
            continue
        if e.section in replace_sections and (scope is None or e.scope == scope):
            continue
        if not (root / e.png).is_file():
            continue
        kept.append(e)
    now = _now()
    for e in entries:
        if not e.created:
            e.created = now
    allents = kept + list(entries)
    atomic_write(root / MANIFEST, json.dumps({"title": title, "updated": now,
                                               "entries": [asdict(e) for e in allents]}, indent=1, default=str))
    atomic_write(html_path, render_html(allents, title, links or {}, intro))
    return html_path


def render_html(entries: list[GalleryEntry], title: str, links: dict, intro: str | None = None) -> str:
    """The gallery page: sections in the order of ``SECTIONS``, newest first within a section."""
    esc = html.escape
    parts = [f"<h1>{esc(title)}</h1>"]
    if links:
        parts.append("<p class='links'>" + " · ".join(f"<a href='{esc(h, quote=True)}'>{esc(k)}</a>"
                                                    for k, h in links.items()) + "</p>")
    parts.append("<p class='intro'>" + esc(intro or (
        "Stereo figures: the estimator's inliers, each coloured by its error against the ground truth — green "
        "(0 px) to yellow (5 px), red above 5 px, blue where it cannot be computed; the legend of each figure "
        "says whether the error is the reprojection error through depth maps or the symmetric epipolar "
        "distance to the ground-truth F. Multiview figures: keypoints in the 3D model in blue, the others in "
        "red. Click a figure for full size.")) + "</p>")
    order = list(SECTIONS) + sorted({e.section for e in entries} - set(SECTIONS))
    if not entries:
        parts.append("<p><i>no figures yet</i></p>")
    for sec in order:
        es = [e for e in entries if e.section == sec]
        if not es:
            continue
        es.sort(key=lambda e: e.created, reverse=True)
        wide = sec in ("compare", "multiview")
        parts.append(f"<h2>{esc(SECTIONS.get(sec, sec))} <span class='n'>({len(es)})</span></h2>")
        parts.append(f"<div class='grid{' wide' if wide else ''}'>")
        for e in es:
            href = esc(e.png, quote=True)
            cap = f"<b>{esc(e.title)}</b>" + "".join(f"<br>{esc(str(x))}" for x in e.lines)
            parts.append(f"<figure><a href='{href}'><img src='{href}' loading='lazy' alt='{esc(e.title, quote=True)}'>"
                         f"</a><figcaption>{cap}</figcaption></figure>")
        parts.append("</div>")
    style = ("body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1700px;padding:0 1em;color:#222}"
             "h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ddd}"
             ".n{color:#888;font-weight:normal}.intro{color:#555;max-width:70em}"
             ".grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(760px,1fr));gap:18px}"
             ".grid.wide{grid-template-columns:1fr}"
             "figure{margin:0;border:1px solid #e3e3e3;border-radius:6px;padding:6px;background:#fafafa}"
             "figure img{width:100%;height:auto;display:block}"
             "figcaption{font-size:.85em;color:#444;margin-top:4px;word-break:break-word}")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>" + esc(title) + "</title><style>" + style +
            "</style></head><body>\n" + "\n".join(parts) + "\n<p class='intro'>updated " + esc(_now()) +
            "</p></body></html>\n")


def link_gallery(report_path: str | Path, href: str = "gallery.html",
                 label: str = "Qualitative figures (gallery)") -> bool:
    """Add a link to the gallery at the top of an existing HTML report (once). Returns True if the report
    exists and links to it (now or already)."""
    p = Path(report_path)
    if not p.is_file():
        return False
    try:
        text = p.read_text()
    except (OSError, ValueError):  # unreadable, or not UTF-8 text: not our report, left alone
        return False
    if LINK_MARKER in text:
        return True
    link = f"{LINK_MARKER}<p><a href='{html.escape(href, quote=True)}'>{html.escape(label)}</a></p>"
    low = text.lower()
    k = low.find("<body")
    if k >= 0:
        end = text.find(">", k)
        text = text[:end + 1] + link + text[end + 1:]
    else:
        text = link + text
    atomic_write(p, text)
    return True
