"""The coding agent's parts: which code of a model's text is its answer (``extract``), running it
against unit tests in the sandbox (``testing``, with the in-sandbox ``harness``), the ``code_tests``
verifier (``verifier``) and the write-run-fix environment ``code_runner`` (``env``).

Importing :mod:`infinirl.agents.coding.verifier` registers the verifiers; importing
:mod:`infinirl.agents.coding.env` registers the environment. See docs/agents.md, "Coding agent".
"""

from infinirl.agents.coding.extract import ExtractedCode, code_blocks, extract_code
from infinirl.agents.coding.spec import CodeSpec
from infinirl.agents.coding.testing import (
    CodeTestReport,
    TestFailure,
    format_report,
    run_code_tests,
    run_code_tests_sync,
)

__all__ = [
    "CodeSpec",
    "CodeTestReport",
    "ExtractedCode",
    "TestFailure",
    "code_blocks",
    "extract_code",
    "format_report",
    "run_code_tests",
    "run_code_tests_sync",
]
