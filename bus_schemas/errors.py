"""Typed decode errors. Every problem with a bus payload is a ``SchemaError``.

Decoding raises nothing else, whatever the bytes (numpy and msgpack errors
are turned into ``MalformedPayload``, naming the schema and the field). A
stage catches ``SchemaError`` around decoding, counts it by class name in
NodeStats ``errors_by_kind``, logs one line per kind (rate-limited) and keeps
going; nothing here is ever fatal to a process.
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
    """The payload exceeds the size limit for one message (its schema's ``MAX_BYTES``), found before unpacking."""


class OutOfRange(MalformedPayload):
    """A value outside the range its schema states (a ``Range`` annotation): the message is rejected."""
