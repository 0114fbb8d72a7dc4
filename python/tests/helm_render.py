"""A small renderer for the Go-template subset deploy/helm/tether uses, so its templates can be rendered and parsed in
the default test run without the helm binary.

It implements, with Go's text/template semantics: actions `{{ }}` with the `{{-` / `-}}` whitespace trim markers and
`{{/* */}}` comments; `if` / `else if` / `else` / `end`, `range` (over a list or map; `.` is the element), `with`,
`define` and `include`; pipelines (`a | f x`: the piped value is the last argument) with parenthesised sub-pipelines;
fields of `.` and `$` (`.Values.cache.type`), string and integer literals; and the functions default, quote, toYaml,
nindent, indent, trunc, trimSuffix, printf (%s, %d, %v), eq, ne, not, and, or, toString, int. Anything else (another
function, a variable, a construct) raises TemplateError naming it: a template that uses more than this subset fails
the test instead of being rendered wrongly. A missing field renders as "" (Helm turns "<no value>" into "" too).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import yaml


class TemplateError(Exception):
    pass


_ACTION = re.compile(r"\{\{(-?)(.*?)(-?)\}\}", re.S)
_EXPR_TOKEN = re.compile(
    r"\s*(?:"
    r'(?P<str>"(?:[^"\\]|\\.)*")'
    r"|(?P<num>-?\d+)"
    r"|(?P<field>\$?(?:\.[A-Za-z_][A-Za-z0-9_]*)+|\.|\$)"
    r"|(?P<ident>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op>[()|]))"
)


# -- parsing --------------------------------------------------------------------------------------------------


def _split(source: str) -> List[Tuple[str, str]]:
    """The template as ("text", s) and ("action", expr) pieces, trim markers applied to the text around them."""
    pieces: List[Tuple[str, str]] = []
    pos = 0
    trim_next = False
    for m in _ACTION.finditer(source):
        text = source[pos:m.start()]
        if trim_next:
            text = text.lstrip()
        left, body, right = m.group(1), m.group(2), m.group(3)
        if left == "-":
            text = text.rstrip()
        pieces.append(("text", text))
        body = body.strip()
        if not (body.startswith("/*") and body.endswith("*/")):
            pieces.append(("action", body))
        trim_next = right == "-"
        pos = m.end()
    text = source[pos:]
    pieces.append(("text", text.lstrip() if trim_next else text))
    return pieces


class _Parser:
    def __init__(self, pieces: List[Tuple[str, str]], defines: Dict[str, list]) -> None:
        self.pieces = pieces
        self.i = 0
        self.defines = defines

    def parse(self, stop: Tuple[str, ...] = ()) -> Tuple[list, Optional[str]]:
        """Nodes up to one of the `stop` keywords (returned, with its action's text)."""
        nodes: list = []
        while self.i < len(self.pieces):
            kind, value = self.pieces[self.i]
            self.i += 1
            if kind == "text":
                if value:
                    nodes.append(("text", value))
                continue
            word = value.split(None, 1)[0] if value else ""
            if word in stop:
                return nodes, value
            if word == "if":
                nodes.append(self._if(value[2:].strip()))
            elif word in ("range", "with"):
                body, end = self.parse(("else", "end"))
                other: list = []
                if end == "else":
                    other, _ = self.parse(("end",))
                nodes.append((word, value[len(word):].strip(), body, other))
            elif word == "define":
                name = json.loads(value[len("define"):].strip())
                body, _ = self.parse(("end",))
                self.defines[name] = body
            elif word in ("end", "else", "template", "block") or value.startswith("$"):
                raise TemplateError(f"unsupported or misplaced action {{{{ {value} }}}}")
            else:
                nodes.append(("action", value))
        if stop:
            raise TemplateError(f"missing {{{{ end }}}} (expected one of {stop})")
        return nodes, None

    def _if(self, cond: str) -> tuple:
        branches = []
        body, end = self.parse(("else", "end"))
        branches.append((cond, body))
        other: list = []
        while end is not None and end.startswith("else"):
            rest = end[len("else"):].strip()
            if rest.startswith("if "):
                body, end = self.parse(("else", "end"))
                branches.append((rest[3:].strip(), body))
            else:
                other, end = self.parse(("end",))
        return ("if", branches, other)


# -- expressions ----------------------------------------------------------------------------------------------


def _tokens(expr: str) -> List[Tuple[str, str]]:
    out = []
    pos = 0
    expr = expr.rstrip()
    while pos < len(expr):
        m = _EXPR_TOKEN.match(expr, pos)
        if not m or m.end() == pos:
            raise TemplateError(f"cannot parse expression {expr!r} at {expr[pos:]!r}")
        kind = m.lastgroup
        out.append((kind, m.group(kind)))
        pos = m.end()
    return out


def _truthy(v: Any) -> bool:
    return v not in (None, False, 0, "") and not (isinstance(v, (list, dict)) and len(v) == 0)


def _to_text(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    if isinstance(v, (list, dict)):
        raise TemplateError(f"printing a {type(v).__name__} directly (use toYaml): {v!r}")
    return str(v)


def _go_printf(fmt: str, *args: Any) -> str:
    out, it = [], iter(args)

    def sub(m: "re.Match[str]") -> str:
        verb = m.group(1)
        if verb == "%":
            return "%"
        return _to_text(next(it))

    out.append(re.sub(r"%([sdv%])", sub, fmt))
    return "".join(out)


def _to_yaml(v: Any) -> str:
    if v in (None, {}, []):
        return "{}" if v in (None, {}) else "[]"
    return yaml.safe_dump(v, default_flow_style=False, sort_keys=True).rstrip("\n")


def _indent(n: int, s: str) -> str:
    return "\n".join(" " * int(n) + line for line in str(s).split("\n"))


def _and(*args: Any) -> Any:
    for a in args:
        if not _truthy(a):
            return a
    return args[-1]


def _or(*args: Any) -> Any:
    for a in args:
        if _truthy(a):
            return a
    return args[-1]


class Renderer:
    def __init__(self, defines: Dict[str, list]) -> None:
        self.defines = defines
        self.funcs: Dict[str, Callable[..., Any]] = {
            "default": lambda d, v=None: v if _truthy(v) else d,
            "quote": lambda v: json.dumps(_to_text(v)),
            "toYaml": _to_yaml,
            "nindent": lambda n, s: "\n" + _indent(n, s),
            "indent": _indent,
            "trunc": lambda n, s: str(s)[: int(n)],
            "trimSuffix": lambda suf, s: str(s)[: -len(suf)] if suf and str(s).endswith(suf) else str(s),
            "printf": _go_printf,
            "eq": lambda a, b: a == b,
            "ne": lambda a, b: a != b,
            "not": lambda v: not _truthy(v),
            "and": _and,
            "or": _or,
            "toString": _to_text,
            "int": lambda v: int(v),
            "include": self._include,
        }

    def _include(self, name: str, dot: Any) -> str:
        if name not in self.defines:
            raise TemplateError(f"include of undefined template {name!r}")
        return self.render(self.defines[name], dot, dot)

    # A pipeline: commands separated by |, each a function call or a single operand.
    def eval(self, expr: str, dot: Any, root: Any) -> Any:
        toks = _tokens(expr)
        value, rest = self._pipeline(toks, dot, root)
        if rest:
            raise TemplateError(f"unexpected {rest[0][1]!r} in {expr!r}")
        return value

    def _pipeline(self, toks: List[Tuple[str, str]], dot: Any, root: Any) -> Tuple[Any, list]:
        piped: Any = _NOTHING
        while True:
            value, toks = self._command(toks, dot, root, piped)
            piped = value
            if toks and toks[0] == ("op", "|"):
                toks = toks[1:]
                continue
            return value, toks

    def _command(self, toks: list, dot: Any, root: Any, piped: Any) -> Tuple[Any, list]:
        if not toks:
            raise TemplateError("empty command")
        head = toks[0]
        if head[0] == "ident":
            name = head[1]
            if name in ("true", "false", "nil"):
                args, toks = [], toks[1:]
                value = {"true": True, "false": False, "nil": None}[name]
                if piped is not _NOTHING:
                    raise TemplateError(f"cannot pipe into {name}")
                return value, toks
            if name not in self.funcs:
                raise TemplateError(f"unsupported function {name!r}")
            args, toks = self._operands(toks[1:], dot, root)
            if piped is not _NOTHING:
                args.append(piped)
            return self.funcs[name](*args), toks
        args, toks = self._operands(toks, dot, root)
        if len(args) != 1 or piped is not _NOTHING:
            raise TemplateError(f"a non-function command takes one operand: {args!r}")
        return args[0], toks

    def _operands(self, toks: list, dot: Any, root: Any) -> Tuple[list, list]:
        args = []
        while toks and toks[0] not in (("op", "|"), ("op", ")")):
            kind, text = toks[0]
            if kind == "op" and text == "(":
                value, toks = self._pipeline(toks[1:], dot, root)
                if not toks or toks[0] != ("op", ")"):
                    raise TemplateError("missing )")
                args.append(value)
                toks = toks[1:]
                continue
            if kind == "str":
                args.append(json.loads(text))
            elif kind == "num":
                args.append(int(text))
            elif kind == "field":
                args.append(self._field(text, dot, root))
            elif kind == "ident":
                raise TemplateError(f"function {text!r} used as an argument (parenthesise it)")
            toks = toks[1:]
        return args, toks

    @staticmethod
    def _field(path: str, dot: Any, root: Any) -> Any:
        if path == ".":
            return dot
        base = root if path.startswith("$") else dot
        for part in path.lstrip("$").split(".")[1:]:
            if isinstance(base, dict):
                base = base.get(part)
            else:
                return None
        return base

    def render(self, nodes: list, dot: Any, root: Any) -> str:
        out: List[str] = []
        for node in nodes:
            kind = node[0]
            if kind == "text":
                out.append(node[1])
            elif kind == "action":
                out.append(_to_text(self.eval(node[1], dot, root)))
            elif kind == "if":
                for cond, body in node[1]:
                    if _truthy(self.eval(cond, dot, root)):
                        out.append(self.render(body, dot, root))
                        break
                else:
                    out.append(self.render(node[2], dot, root))
            elif kind == "with":
                value = self.eval(node[1], dot, root)
                out.append(self.render(node[2], value, root) if _truthy(value) else self.render(node[3], dot, root))
            elif kind == "range":
                value = self.eval(node[1], dot, root)
                items = list(value.values()) if isinstance(value, dict) else list(value or [])
                if items:
                    out.extend(self.render(node[2], item, root) for item in items)
                else:
                    out.append(self.render(node[3], dot, root))
        return "".join(out)


_NOTHING = object()


def merge(base: Dict[str, Any], override: Dict[str, Any]) -> Dict[str, Any]:
    """Values merged as helm --set / -f does: maps recursively, anything else replaced."""
    out = dict(base)
    for k, v in override.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def render_string(source: str, values: Dict[str, Any], helpers: str = "") -> str:
    """Renders one template string with `.Values` = values (for the renderer's own tests)."""
    defines: Dict[str, list] = {}
    _Parser(_split(helpers), defines).parse()
    nodes, _ = _Parser(_split(source), defines).parse()
    ctx = {"Values": values, "Release": {"Name": "r", "Namespace": "default", "Service": "Helm"},
           "Chart": {"Name": "c", "Version": "0", "AppVersion": "0"}}
    return Renderer(defines).render(nodes, ctx, ctx)


def render_chart(chart: Path, overrides: Optional[Dict[str, Any]] = None, release: str = "robots",
                 namespace: str = "default") -> Dict[str, str]:
    """Renders every template of `chart` (as `helm template <release> <chart>` would): {template name: text}.
    Files starting with `_` only define templates."""
    meta = yaml.safe_load((chart / "Chart.yaml").read_text())
    values = merge(yaml.safe_load((chart / "values.yaml").read_text()) or {}, overrides or {})
    defines: Dict[str, list] = {}
    parsed = {}
    for path in sorted((chart / "templates").iterdir()):
        nodes, _ = _Parser(_split(path.read_text()), defines).parse()
        parsed[path.name] = nodes
    ctx = {
        "Values": values,
        "Release": {"Name": release, "Namespace": namespace, "Service": "Helm"},
        "Chart": {"Name": meta["name"], "Version": meta["version"], "AppVersion": meta.get("appVersion", "")},
    }
    renderer = Renderer(defines)
    return {name: renderer.render(nodes, ctx, ctx) for name, nodes in parsed.items()
            if not name.startswith("_") and name.endswith((".yaml", ".yml"))}
