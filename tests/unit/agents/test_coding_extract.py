"""Which code of a model's text the coding verifier and environment run (the documented rule)."""

import random

from infinirl.agents.coding.extract import code_blocks, extract_code, stub_preamble

STUB = ('from typing import List\n\n\ndef helper(x):\n    return x\n\n\n'
        'def total(xs: List[int]) -> int:\n    """Sum."""\n')


def test_the_last_python_block_defining_the_entry_point_wins():
    text = ("First try:\n```python\ndef total(xs):\n    return 0\n```\nBetter:\n```python\ndef total(xs):\n"
            "    return sum(xs)\n```\nUsage:\n```python\nprint(total([1]))\n```\n")
    assert extract_code(text, "total").code == "def total(xs):\n    return sum(xs)\n"
    assert extract_code(text).code == "print(total([1]))\n"  # without an entry point: the last block


def test_non_python_blocks_are_skipped_and_bare_fences_count():
    text = "```text\nnot code\n```\n```\ndef f():\n    return 1\n```\n```bash\nls\n```"
    found = extract_code(text, "f")
    assert found.code == "def f():\n    return 1\n" and found.fenced
    assert [(lang, closed) for lang, _, closed in code_blocks(text)] == [("text", True), ("", True), ("bash", True)]


def test_an_unclosed_block_at_the_end_is_read_to_the_end():
    found = extract_code("```python\ndef f(x):\n    return x + 1", "f")
    assert found.code == "def f(x):\n    return x + 1"
    assert code_blocks("```python\ndef f(x):\n    return x + 1")[-1][2] is False


def test_text_without_fences_is_the_code_and_blank_text_is_none():
    assert extract_code("def f():\n    return 2\n", "f").code == "def f():\n    return 2\n"
    assert not extract_code("def f():\n    return 2\n", "f").fenced
    assert extract_code("   \n", "f") is None
    assert extract_code("```python\n\n```", "f") is None


def test_a_body_completes_the_stub_and_is_indented_when_flush_left():
    found = extract_code("return sum(xs)", "total", STUB)
    assert found.completed_stub and found.code == STUB.rstrip() + "\n    return sum(xs)\n"
    indented = extract_code("    s = 0\n    for x in xs:\n        s += x\n    return s\n", "total", STUB)
    assert indented.code.endswith('"""Sum."""\n    s = 0\n    for x in xs:\n        s += x\n    return s\n')


def test_a_full_function_gets_the_stubs_preamble_with_future_imports_first():
    assert stub_preamble(STUB, "total") == 'from typing import List\n\n\ndef helper(x):\n    return x\n\n\n'
    code = extract_code("```python\nfrom __future__ import annotations\ndef total(xs: List[int]) -> int:\n"
                        "    return sum(map(helper, xs))\n```", "total", STUB).code
    assert code.startswith("from __future__ import annotations\nfrom typing import List\n")
    assert code.count("from __future__") == 1 and code.endswith("return sum(map(helper, xs))\n")
    compile(code, "solution.py", "exec")


def test_random_text_never_raises():
    rng = random.Random(0)
    pieces = ["```", "```python\n", "\n", "def f(", "):", "    return 1", "text", "``", "`", " ", "python"]
    for _ in range(2000):
        text = "".join(rng.choice(pieces) for _ in range(rng.randint(0, 12)))
        found = extract_code(text, "f", "def f():\n    pass\n")
        assert found is None or isinstance(found.code, str)
