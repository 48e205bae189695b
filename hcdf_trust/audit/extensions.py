"""Extensions: domains and versions the registry does not know, content failing the registered
schema. Every document of the tree is checked by :func:`hcdf_trust.registry.validation.check_document`."""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from ..include.resolver import Resolution
from .report import ALWAYS, Finding, Report

_CHECKS = {"extension-unregistered", "extension-content"}


def check(report: Report, res: Resolution, schemas: Any) -> None:
    """``schemas`` is a :class:`~hcdf_trust.registry.validation.RegistrySchemaSource`.

    Raises:
        AttackError, TransportError: the registry does not verify or cannot be reached.
    """
    from ..registry.validation import check_document

    for url, doc in res.documents.items():
        path = Path(unquote(urlsplit(url).path)) if url.startswith("file://") else None
        for f in check_document(doc.tree, source=doc.source, path=path, schemas=schemas):
            if f.code in _CHECKS:
                report.add(f.code, f.message, file=f.file, line=f.line)
            elif f.severity == "error":  # a registered stream profile whose digest differs
                report.findings.append(Finding(ALWAYS, f.code, "error", f.message, file=f.file, line=f.line))
