"""MkDocs hooks (``hooks:`` in mkdocs.yml): the site shows the repository's own pages, said once.

The README, CONTRIBUTING.md and results/README.md live outside ``docs/`` because GitHub shows them
there; the site includes them as generated pages (:data:`INCLUDED`) instead of keeping copies. Every
page's relative links are written for the repository, so they are rewritten for the site:

* a link to a page under ``docs/`` or to an included page points at that page in the site;
* an image outside ``docs/`` (``results/skygen/preview.png``) is copied into the site under ``_repo/``;
* a link to any other repository file (a results report, a config, ``LICENSE``) points at the file on
  the repository host when ``repo_url`` is set in mkdocs.yml, and is otherwise shown as its path in
  code, so that no link of the site leads nowhere.

Links are rewritten outside fenced code blocks and inline code only. In the API reference, the
docstrings' reST cross-reference roles (``:class:`~skygen.errors.ConfigError```), which the numpy-style
renderer shows as text, are shown as the code they name.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
# site page -> repository file
INCLUDED = {"index.md": "README.md", "contributing.md": "CONTRIBUTING.md", "results.md": "results/README.md"}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".svg", ".gif")
COPIED = "_repo"
LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")
FENCE_OR_CODE = re.compile(r"(^```.*?^```[^\n]*$|`[^`\n]+`)", re.DOTALL | re.MULTILINE)
ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|exc|obj|const):<code>~?([^<]*)</code>")


def _repo_path(src_uri: str) -> str:
    """Where a site page lives in the repository."""
    return INCLUDED.get(src_uri, "docs/" + src_uri)


def _targets(markdown: str):
    """(is image, text, target) of every link outside code."""
    for i, part in enumerate(FENCE_OR_CODE.split(markdown)):
        if i % 2 == 0:
            yield from LINK.findall(part)


def _resolve(page_repo: str, target: str) -> tuple[str, str] | None:
    """(repository path, '#anchor' or '') of a relative link, None for URLs and anchors."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
        return None
    path, _, anchor = target.partition("#")
    repo = posixpath.normpath(posixpath.join(posixpath.dirname(page_repo), path))
    return repo, ("#" + anchor if anchor else "")


def _outside_image(hit: tuple[str, str] | None) -> str | None:
    """The repository path of a linked image that lives outside ``docs/``, else None."""
    if hit is None or hit[0].startswith("docs/") or not hit[0].lower().endswith(IMAGE_SUFFIXES):
        return None
    return hit[0] if (ROOT / hit[0]).is_file() else None


def on_files(files: Files, config) -> Files:
    for src_uri, repo in INCLUDED.items():
        files.append(File.generated(config, src_uri, abs_src_path=str(ROOT / repo)))
    copied: set[str] = set()
    for f in list(files):
        if not f.src_uri.endswith(".md") or f.abs_src_path is None:
            continue
        for image, _, target in _targets(Path(f.abs_src_path).read_text(encoding="utf-8")):
            path = _outside_image(_resolve(_repo_path(f.src_uri), target)) if image else None
            if path and path not in copied:
                copied.add(path)
                files.append(File.generated(config, f"{COPIED}/{path}", abs_src_path=str(ROOT / path)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    here = posixpath.dirname(page.file.src_uri)
    site_of = {repo: uri for uri, repo in INCLUDED.items()}
    repo_url = (config.get("repo_url") or "").rstrip("/")

    def rewrite(m: re.Match) -> str:
        image, text, target = m.groups()
        hit = _resolve(_repo_path(page.file.src_uri), target)
        if hit is None:
            return m.group(0)
        repo, anchor = hit
        if repo.startswith("docs/"):
            site = repo[len("docs/") :]
        elif repo in site_of:
            site = site_of[repo]
        elif image and repo.lower().endswith(IMAGE_SUFFIXES):
            site = f"{COPIED}/{repo}"
        elif repo_url:
            return f"{image}[{text}]({repo_url}/blob/HEAD/{repo}{anchor})"
        else:
            return text if f"`{repo}`" in text or repo in text.strip("`/") else f"{text} (`{repo}`)"
        return f"{image}[{text}]({posixpath.relpath(site, here or '.')}{anchor})"

    parts = FENCE_OR_CODE.split(markdown)
    return "".join(part if i % 2 else LINK.sub(rewrite, part) for i, part in enumerate(parts))


def on_page_content(html: str, page, config, files) -> str:
    return ROLE.sub(r"<code>\1</code>", html) if page.file.src_uri.startswith("api/") else html
