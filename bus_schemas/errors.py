"""Typed decode errors. Every problem with a bus payload is a ``SchemaError``.

A stage catches ``SchemaError`` around decoding, logs one line, counts it by
class name and keeps going; nothing here is ever fatal to a process.
"""

from __future__ import annotations


class SchemaError(Exception):
    """A payload that this build cannot turn into a message."""


class UnknownSchema(SchemaError):
    """The envelope names a schema that is not in the registry."""


class WrongSchema(SchemaError):
    """The envelope names another schema than the one the port expects."""


class WrongVersion(SchemaError):
    """The schema is known but the payload's version is not one this build reads."""


class MalformedPayload(SchemaError):
    """The bytes are not a valid envelope, or the body does not match the schema."""


class PayloadTooLarge(MalformedPayload):
    """The payload exceeds the size limit for one message."""
