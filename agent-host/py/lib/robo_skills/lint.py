"""The check that keeps base-frame coordinates out of a skill's code, on the parsed code.

A skill must work wherever its objects are now, so a position in its code must come from
perception or a rule, never from a number written down. On the syntax tree (`ast`):

- numbers are folded first (``0.2 + 0.1``, ``2 * 0.15``, ``-(0.3)`` are numbers);
- a literal sequence of 3, 6 or 7 numbers (a position, a pose, a waypoint), or ``np.array`` of
  one, is refused unless it is a *difference*: an operand of ``+`` or ``-`` whose other operand
  is not itself constant (``here + [0, 0, 0.1]``; ``[0.5, 0, 0.3] + [0, 0, 0.1]`` is still a
  fixed position), or of ``+=``/``-=``, or the value of a rule keyword (``offset_m=``,
  ``axis=``, ``tilt_rad=``); a sequence of only 0 and ±1 (an axis, a unit vector) is always
  allowed; an ``offset_m=`` longer than 0.4 m is refused (no grasp or approach offset is that
  long: it is a position in disguise);
- assigning a fixed number to an element (``goal[2] = 0.3``, also inside a tuple assignment
  ``goal[0], goal[1] = 0.5, 0.1``) is refused: that sets a coordinate; ``goal[2] += 0.1``
  moves it and is allowed;
- code that does not parse or compile is refused with the line.

`check_code(text)` returns nothing or raises `LintError` naming every offending line.
"""

from __future__ import annotations

import ast

RULE_KEYWORDS = {"offset_m", "axis", "tilt_rad"}
POSE_LENGTHS = {3, 6, 7}
MAX_OFFSET_M = 0.4


class LintError(ValueError):
    """Code a skill may not carry; the message names each line and why."""


def _number(n: ast.AST) -> float | None:
    if isinstance(n, ast.Constant) and isinstance(n.value, (int, float)) and not isinstance(n.value, bool):
        return float(n.value)
    if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd)):
        v = _number(n.operand)
        return None if v is None else (-v if isinstance(n.op, ast.USub) else v)
    if isinstance(n, ast.BinOp) and isinstance(n.op, (ast.Add, ast.Sub, ast.Mult, ast.Div)):
        a, b = _number(n.left), _number(n.right)
        if a is None or b is None:
            return None
        try:
            return {ast.Add: a + b, ast.Sub: a - b, ast.Mult: a * b, ast.Div: a / b if b else None}[type(n.op)]
        except OverflowError:
            return None
    return None


CONSTRUCTORS = {"zeros", "ones", "full", "array", "asarray"}
"""numpy calls whose result is fixed when their arguments are numbers."""


def _constant(n: ast.AST) -> bool:
    """Whether ``n`` is made of numbers only: a number, a literal sequence of numbers (also
    repeated, ``[0.3] * 3``), a numpy constructor of numbers (``np.zeros(3)``), sums of them."""
    if _number(n) is not None or _literal_pose(n) is not None:
        return True
    if isinstance(n, (ast.List, ast.Tuple)):
        return all(_number(e) is not None for e in n.elts)
    if isinstance(n, ast.Call) and getattr(n.func, "attr", getattr(n.func, "id", "")) in CONSTRUCTORS:
        return all(_constant(a) for a in n.args) and all(_constant(k.value) for k in n.keywords)
    if isinstance(n, ast.BinOp) and isinstance(n.op, (ast.Add, ast.Sub, ast.Mult)):
        return _constant(n.left) and _constant(n.right)
    return False


def _literal_pose(n: ast.AST) -> list[float] | None:
    """The numbers of a list/tuple display (or np.array/np.asarray/array of one) of 3, 6 or 7
    numbers, else None."""
    if isinstance(n, ast.Call) and n.args and getattr(n.func, "attr", getattr(n.func, "id", "")) in ("array", "asarray"):
        return _literal_pose(n.args[0])
    if isinstance(n, (ast.List, ast.Tuple)) and len(n.elts) in POSE_LENGTHS:
        vals = [_number(e) for e in n.elts]
        if all(v is not None for v in vals):
            return [float(v) for v in vals if v is not None]
    return None


class _Linter(ast.NodeVisitor):
    def __init__(self) -> None:
        self.problems: list[str] = []
        self.allowed: set[int] = set()  # ids of literal nodes used as differences or rule fields

    def _allow(self, n: ast.AST) -> None:
        self.allowed.add(id(n))
        if isinstance(n, ast.Call) and n.args:
            self.allowed.add(id(n.args[0]))

    def visit_BinOp(self, node: ast.BinOp) -> None:
        if isinstance(node.op, ast.Mult):
            self.visit_BinOp_repeat(node)
        if isinstance(node.op, (ast.Add, ast.Sub)):
            # A difference moves something measured; constant + constant is a fixed position.
            if not _constant(node.right):
                self._allow(node.left)
            if not _constant(node.left):
                self._allow(node.right)
        self.generic_visit(node)

    def visit_AugAssign(self, node: ast.AugAssign) -> None:
        if isinstance(node.op, (ast.Add, ast.Sub)):
            self._allow(node.value)
        self.generic_visit(node)

    def visit_keyword(self, node: ast.keyword) -> None:
        if node.arg in RULE_KEYWORDS:
            self._allow(node.value)
            vals = _literal_pose(node.value)
            if node.arg == "offset_m" and vals is not None and sum(v * v for v in vals[:3]) ** 0.5 > MAX_OFFSET_M:
                self.problems.append(
                    f"line {node.lineno}: offset_m={[round(v, 4) for v in vals]} is longer than {MAX_OFFSET_M} m: "
                    "that is a position, not an offset from the object")
        self.generic_visit(node)

    def _sets(self, target: ast.AST, value: ast.AST, line: int) -> None:
        if isinstance(target, (ast.Tuple, ast.List)) and isinstance(value, (ast.Tuple, ast.List)):
            for t, v in zip(target.elts, value.elts):
                self._sets(t, v, line)
            return
        v = _number(value)
        if v is not None and v != 0.0 and isinstance(target, ast.Subscript):
            self.problems.append(f"line {line}: sets a coordinate to the fixed number {v:g} "
                                 "(move it relative to a measured or bound pose instead, e.g. with +=)")

    def visit_Assign(self, node: ast.Assign) -> None:
        for t in node.targets:
            self._sets(t, node.value, node.lineno)
        self.generic_visit(node)

    def _literal(self, node: ast.AST) -> None:
        vals = _literal_pose(node)
        if vals is not None and id(node) not in self.allowed and not all(v in (0.0, 1.0, -1.0) for v in vals):
            self.problems.append(
                f"line {node.lineno}: {[round(v, 4) for v in vals]} looks like a base-frame position or pose "
                "written into the code; bind a rule to the object seen now (robo_skills.bind) or add an "
                "offset to a measured pose")
            self.allowed.add(id(node))  # said once
            if isinstance(node, ast.Call) and node.args:
                self.allowed.add(id(node.args[0]))

    def visit_BinOp_repeat(self, node: ast.BinOp) -> None:
        """``[0.3, 0.1] * 3``-style repetition: a fixed sequence of pose length."""
        seq, times = (node.left, node.right) if isinstance(node.left, (ast.List, ast.Tuple)) else (node.right, node.left)
        k = _number(times)
        if isinstance(seq, (ast.List, ast.Tuple)) and k is not None and k == int(k):
            vals = [_number(e) for e in seq.elts]
            if vals and all(v is not None for v in vals) and len(vals) * int(k) in POSE_LENGTHS \
                    and id(node) not in self.allowed and not all(v in (0.0, 1.0, -1.0) for v in vals):
                self.problems.append(
                    f"line {node.lineno}: {[round(v, 4) for v in vals if v is not None]} * {int(k)} builds a fixed "
                    "base-frame position; bind a rule to the object seen now instead")
                self.allowed.update({id(node), id(seq)})

    def visit_List(self, node: ast.List) -> None:
        self._literal(node)
        self.generic_visit(node)

    def visit_Tuple(self, node: ast.Tuple) -> None:
        self._literal(node)
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        # keywords and operands first, so that an allowed np.array(...) is known before it is judged
        for k in node.keywords:
            self.visit(k)
        self._literal(node)
        self.visit(node.func)
        for a in node.args:
            self.visit(a)


def check_code(text: str, name: str = "<skill code>") -> None:
    """Raises LintError when ``text`` does not compile or writes base-frame coordinates."""
    try:
        tree = ast.parse(text, filename=name)
        compile(tree, name, "exec")
    except SyntaxError as e:
        raise LintError(f"{name}: line {e.lineno}: {e.msg}") from None
    linter = _Linter()
    # differences are marked before the literals inside them are judged: visit parents first
    linter.visit(tree)
    if linter.problems:
        raise LintError(f"{name}: " + "; ".join(linter.problems))
