"""Fixtures shared by the tests and the bench scripts (not used by the pipeline itself).

- ``samples``: one deterministic sample message per registered schema (the golden payloads are made from them);
- ``mutations``: seeded mutations of the golden payloads and targeted hostile payloads for the decoder;
- ``adversarial``: recordings with one tracker oddity each, written in the INTERACTION layout the loader reads;
- ``big_frames``: well-formed TrackFrames of hundreds to thousands of objects made from real K729 tracks;
- ``helpers``: processes and ports for tests that run real stages on the loopback bus.

``helpers``, ``mutations`` and ``adversarial`` read files of a source
checkout (the golden payloads, the repository root as working directory).
"""
