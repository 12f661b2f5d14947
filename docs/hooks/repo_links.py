"""MkDocs hook: links from a docs page to a file of the repository outside ``docs/``.

A page such as ``validation.md`` links ``../studies/crosscheck/results/error_vs_time.png``: on GitHub that is
the file beside the page, but the site holds only ``docs/``. This hook copies each such file into the site
under ``repo/`` and points the link there, so the link works in both places; a link to a repository file that
does not exist is logged as a warning, which ``mkdocs build --strict`` (``make docs``) turns into an error.
Markdown files are copied as ``.txt`` (the site shows them as text, not as unlisted pages).
"""

import logging
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File

log = logging.getLogger("mkdocs.hooks.repo_links")

#: ``[text](target)`` or ``![alt](target "title")``; the target without spaces.
LINK = re.compile(r'(!?\[[^\]\n]*\])\(([^)\s]+)((?:\s+"[^"\n]*")?)\)')
EXTERNAL = re.compile(r"^([a-z][a-z0-9+.-]*:|#|/)", re.IGNORECASE)


def on_page_markdown(markdown, page, config, files):
    docs_dir = Path(config["docs_dir"]).resolve()
    repo_root = docs_dir.parent
    page_dir = posixpath.dirname(page.file.src_uri)

    def rewrite(match):
        label, target, title = match.groups()
        if EXTERNAL.match(target):
            return match.group(0)
        path, _, fragment = target.partition("#")
        in_docs = posixpath.normpath(posixpath.join(page_dir, path))
        if not in_docs.startswith("../"):
            return match.group(0)              # a page or image in docs/: MkDocs checks it itself
        repo_path = posixpath.normpath(posixpath.join("docs", in_docs))
        source = repo_root / repo_path
        if repo_path.startswith("../") or not source.is_file():
            log.warning("Doc file '%s' links '%s': no such file in the repository", page.file.src_uri, target)
            return match.group(0)
        site_uri = "repo/" + repo_path + (".txt" if repo_path.endswith(".md") else "")
        if files.get_file_from_path(site_uri) is None:
            files.append(File.generated(config, site_uri, abs_src_path=str(source)))
        link = posixpath.relpath(site_uri, page_dir or ".")
        return f"{label}({link}{'#' + fragment if fragment else ''}{title})"

    return LINK.sub(rewrite, markdown)
