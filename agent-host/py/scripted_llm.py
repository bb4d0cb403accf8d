#!/usr/bin/env python3
"""A scripted LLM HTTP server for testing LLM clients without a real provider.

    python agent-host/py/scripted_llm.py --script FILE [--port 0] [--log DIR]

prints ``LISTENING <port>`` on stdout once it accepts connections and serves on 127.0.0.1
until SIGTERM (or Ctrl-C). Standard library only.

FILE is a recorded conversation ``{"gym", "model", "responses": [str, ...]}``. The reply to a
request is ``responses[k]`` where k is the number of assistant messages in the request, so a
replay is deterministic and stateless; past the end the reply is ``<stop>script exhausted</stop>``.
FILE may also be a cassette recorded by ``--llm record:`` (JSON Lines, agent-host/src/cassette.rs):
``responses[k]`` is then the recorded answer to its request with k assistant messages, whatever
the rest of the request holds (a turn-by-turn replay; ``--llm replay:`` is the strict one).

Two wire formats:

* OpenAI-compatible chat completions, ``POST /v1/chat/completions`` (``Authorization: Bearer``).
* Anthropic Messages, ``POST /v1/messages`` (``x-api-key``, ``anthropic-version``).

Requests are validated strictly (JSON object, required fields and their types, roles in the
right order ending with a user turn, text/image parts well formed, images base64 PNG (or JPEG)
data whose bytes match the declared type, the auth header present). A bad request gets a 400
with the error JSON of that API (OpenAI ``{"error": {...}}``, Anthropic
``{"type": "error", "error": {...}}``); unknown paths get a 404 in the same shapes.

Usage is simulated: tokens = ceil(characters / 4) of each message's text + 800 per image
(the system prompt counts as the first message). What a provider's prompt cache would serve counts
as cached: for OpenAI, the longest prefix of this request's messages that equals the previous
successful request's (OpenAI-compatible servers cache by themselves); for Anthropic, only such a
prefix that ends where the previous request put a ``cache_control`` mark, when this request marks
one at or after it (Anthropic caches nothing unmarked; the marks do not enter the comparison). OpenAI reports it in ``prompt_tokens_details.cached_tokens``
(part of ``prompt_tokens``); Anthropic reports it as ``cache_read_input_tokens`` and leaves it
out of ``input_tokens`` (``cache_creation_input_tokens`` is 0). With the request header
``x-scripted-no-usage-cache: 1`` no cache fields are reported at all (OpenAI: no
``prompt_tokens_details``/``completion_tokens_details``; Anthropic: no ``cache_*`` fields, and
``input_tokens`` is the whole prompt).

Fault modes for client tests, selected by a path prefix before the API path, e.g. base URL
``http://127.0.0.1:PORT/fault/429once`` -> ``POST /fault/429once/v1/chat/completions``:

* ``429once``: the first request of this mode on this server gets 429, ``Retry-After: 0`` and the
  API's rate-limit error JSON; later ones are answered normally.
* ``500once``: the same with 500 and the API's server error JSON.
* ``slow``: waits 30 s, then answers normally (other requests are served meanwhile).
* ``malformed``: 200 with the truncated body ``{"choices": [``.
* ``endless``: 200, ``Transfer-Encoding: chunked``, 64 KiB chunks of spaces until the client
  disconnects.
* ``nojson``: 200 with an HTML body.
* ``cutoff``: the scripted answer cut in half, as an endpoint stops one at its token limit
  (OpenAI ``finish_reason: "length"``, Anthropic ``stop_reason: "max_tokens"``).

``--log DIR`` writes each request body to ``DIR/request-NNN.json`` (base64 image data replaced
by its length: Anthropic ``source.data`` becomes an integer, an OpenAI data URL becomes
``data:<type>;base64,<len=N>``) and each response body to ``DIR/response-NNN.json``
(non-JSON fault bodies are described in a small JSON object instead).
"""

import argparse
import base64
import binascii
import copy
import json
import math
import os
import signal
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

IMAGE_TOKENS = 800
SLOW_S = 30.0
ENDLESS_CHUNK = b" " * (64 * 1024)
MAX_BODY = 256 * 1024 * 1024
EXHAUSTED = "<stop>script exhausted</stop>"
FAULTS = ("429once", "500once", "slow", "malformed", "endless", "nojson", "nocache", "cutoff")
OPENAI_PATH = "/v1/chat/completions"
ANTHROPIC_PATH = "/v1/messages"
ANTHROPIC_VERSIONS = ("2023-06-01", "2023-01-01")
MAGIC = {"image/png": b"\x89PNG\r\n\x1a\n", "image/jpeg": b"\xff\xd8\xff"}


class BadRequest(Exception):
    """A request the real API would refuse with 400 (message, offending parameter)."""

    def __init__(self, message, param=None, code=None):
        super().__init__(message)
        self.message, self.param, self.code = message, param, code


# ---------------------------------------------------------------- validation helpers


def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v):
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _image_bytes(b64, media_type, where):
    """Checks base64 image data strictly: valid base64 and bytes matching the declared type."""
    if not isinstance(b64, str) or not b64:
        raise BadRequest(f"{where}: image data must be a non-empty base64 string", where)
    try:
        raw = base64.b64decode(b64, validate=True)
    except (binascii.Error, ValueError) as e:
        raise BadRequest(f"{where}: image data is not valid base64 ({e})", where)
    magic = MAGIC.get(media_type)
    if magic is None:
        raise BadRequest(f"{where}: unsupported image media type {media_type!r}; "
                         f"supported: {', '.join(MAGIC)}", where)
    if not raw.startswith(magic):
        raise BadRequest(f"{where}: image data is not a valid {media_type} image", where)
    if media_type == "image/png" and (len(raw) < 33 or raw[12:16] != b"IHDR"):
        raise BadRequest(f"{where}: image data is a truncated PNG (no IHDR chunk)", where)
    return raw


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def _text_tokens(text):
    return math.ceil(len(text) / 4)


def _strip_cache_control(v):
    if isinstance(v, dict):
        return {k: _strip_cache_control(x) for k, x in v.items() if k != "cache_control"}
    if isinstance(v, list):
        return [_strip_cache_control(x) for x in v]
    return v


def _marked(content):
    """Whether an Anthropic system prompt or message content holds a cache_control mark."""
    return isinstance(content, list) and any(isinstance(b, dict) and "cache_control" in b for b in content)


def _canon(v):
    return json.dumps(_strip_cache_control(v), sort_keys=True, separators=(",", ":"))


def _check_order(roles, first_system_ok, param="messages"):
    """System messages only at the start, then user/assistant alternating, first and last user."""
    i = 0
    if first_system_ok:
        while i < len(roles) and roles[i] == "system":
            i += 1
    rest = roles[i:]
    if not rest:
        raise BadRequest(f"{param}: at least one user message is required", param)
    for j, r in enumerate(rest):
        want = "user" if j % 2 == 0 else "assistant"
        if r != want:
            raise BadRequest(f"{param}[{i + j}]: expected role {want!r} here, got {r!r} "
                             "(roles must alternate user/assistant, starting with user)",
                             f"{param}[{i + j}].role")
    if rest[-1] != "user":
        raise BadRequest(f"{param}: the last message must have role 'user'", param)


# ---------------------------------------------------------------- OpenAI


def validate_openai(headers, body):
    """Returns [(canonical message, tokens)] of the prompt, raising BadRequest when invalid."""
    auth = headers.get("Authorization", "")
    if not auth.startswith("Bearer ") or not auth[len("Bearer "):].strip():
        raise BadRequest("You didn't provide an API key. You need to provide your API key in an "
                         "Authorization header using Bearer auth (i.e. Authorization: Bearer YOUR_KEY).",
                         None, "invalid_api_key")
    if not isinstance(body, dict):
        raise BadRequest("the request body must be a JSON object")
    if not isinstance(body.get("model"), str) or not body["model"]:
        raise BadRequest("'model' is required and must be a non-empty string", "model")
    if "temperature" in body and body["temperature"] is not None:
        t = body["temperature"]
        if not _is_num(t) or not 0 <= t <= 2:
            raise BadRequest("'temperature' must be a number from 0 to 2", "temperature")
    for k in ("max_tokens", "max_completion_tokens"):
        if k in body and body[k] is not None and (not _is_int(body[k]) or body[k] < 1):
            raise BadRequest(f"'{k}' must be a positive integer", k)
    if body.get("stream"):
        raise BadRequest("streaming is not supported by the scripted server", "stream")
    if "n" in body and body["n"] not in (None, 1):
        raise BadRequest("only n=1 is supported", "n")
    msgs = body.get("messages")
    if not isinstance(msgs, list) or not msgs:
        raise BadRequest("'messages' is required and must be a non-empty array", "messages")
    roles, out = [], []
    for i, m in enumerate(msgs):
        p = f"messages[{i}]"
        if not isinstance(m, dict):
            raise BadRequest(f"{p} must be an object", p)
        role = m.get("role")
        if role not in ("system", "user", "assistant"):
            raise BadRequest(f"{p}.role must be one of 'system', 'user', 'assistant', got {role!r}",
                             f"{p}.role")
        c = m.get("content")
        chars, images = 0, 0
        if isinstance(c, str):
            chars = len(c)
        elif isinstance(c, list):
            if not c:
                raise BadRequest(f"{p}.content must not be an empty array", f"{p}.content")
            for j, part in enumerate(c):
                q = f"{p}.content[{j}]"
                if not isinstance(part, dict):
                    raise BadRequest(f"{q} must be an object", q)
                kind = part.get("type")
                if kind == "text":
                    if not isinstance(part.get("text"), str):
                        raise BadRequest(f"{q}.text must be a string", f"{q}.text")
                    chars += len(part["text"])
                elif kind == "image_url":
                    if role != "user":
                        raise BadRequest(f"{q}: image parts are only allowed in user messages", q)
                    iu = part.get("image_url")
                    if not isinstance(iu, dict) or not isinstance(iu.get("url"), str):
                        raise BadRequest(f"{q}.image_url must be an object with a string 'url'",
                                         f"{q}.image_url")
                    if iu.get("detail", "auto") not in ("auto", "low", "high"):
                        raise BadRequest(f"{q}.image_url.detail must be 'auto', 'low' or 'high'",
                                         f"{q}.image_url.detail")
                    url = iu["url"]
                    head, sep, data = url.partition(",")
                    if not (url.startswith("data:") and sep and head.endswith(";base64")):
                        raise BadRequest(f"{q}.image_url.url must be a data URL "
                                         "'data:image/png;base64,...'", f"{q}.image_url.url")
                    _image_bytes(data, head[len("data:"):-len(";base64")], f"{q}.image_url.url")
                    images += 1
                else:
                    raise BadRequest(f"{q}.type must be 'text' or 'image_url', got {kind!r}",
                                     f"{q}.type")
        else:
            raise BadRequest(f"{p}.content must be a string or an array of content parts",
                             f"{p}.content")
        roles.append(role)
        out.append((_canon({"role": role, "content": c}),
                    math.ceil(chars / 4) + IMAGE_TOKENS * images, False))
    _check_order(roles, True)
    return out, roles.count("assistant")


def openai_error(status, message, etype=None, param=None, code=None):
    etype = etype or {400: "invalid_request_error", 404: "invalid_request_error",
                      429: "requests", 500: "server_error"}.get(status, "api_error")
    return {"error": {"message": message, "type": etype, "param": param, "code": code}}


# ---------------------------------------------------------------- Anthropic


def _anthropic_blocks(c, p, role, allow_images):
    chars, images = 0, 0
    if isinstance(c, str):
        return len(c), 0
    if not isinstance(c, list) or not c:
        raise BadRequest(f"{p}: content must be a string or a non-empty array of content blocks", p)
    for j, b in enumerate(c):
        q = f"{p}.{j}"
        if not isinstance(b, dict):
            raise BadRequest(f"{q}: content block must be an object", q)
        cc = b.get("cache_control")
        if cc is not None and (not isinstance(cc, dict) or cc.get("type") != "ephemeral"):
            raise BadRequest(f"{q}.cache_control: type must be 'ephemeral'", q)
        kind = b.get("type")
        if kind == "text":
            if not isinstance(b.get("text"), str):
                raise BadRequest(f"{q}.text: Field required (a string)", q)
            chars += len(b["text"])
        elif kind == "image":
            if not allow_images:
                raise BadRequest(f"{q}: image blocks are only allowed in user messages", q)
            src = b.get("source")
            if not isinstance(src, dict) or src.get("type") != "base64":
                raise BadRequest(f"{q}.source: must be an object with type 'base64'", q)
            if not isinstance(src.get("media_type"), str):
                raise BadRequest(f"{q}.source.media_type: Field required", q)
            _image_bytes(src.get("data"), src["media_type"], f"{q}.source.data")
            images += 1
        else:
            raise BadRequest(f"{q}.type: expected 'text' or 'image', got {kind!r}", q)
    return chars, images


def validate_anthropic(headers, body):
    key = headers.get("x-api-key", "")
    if not key.strip():
        raise BadRequest("x-api-key header is required", None, "authentication_error")
    ver = headers.get("anthropic-version", "")
    if ver not in ANTHROPIC_VERSIONS:
        raise BadRequest(f"anthropic-version header is required and must be one of "
                         f"{', '.join(ANTHROPIC_VERSIONS)} (got {ver!r})")
    if not isinstance(body, dict):
        raise BadRequest("the request body must be a JSON object")
    if not isinstance(body.get("model"), str) or not body["model"]:
        raise BadRequest("model: Field required (a non-empty string)", "model")
    if not _is_int(body.get("max_tokens")) or body["max_tokens"] < 1:
        raise BadRequest("max_tokens: Field required (a positive integer)", "max_tokens")
    if "temperature" in body and body["temperature"] is not None:
        t = body["temperature"]
        if not _is_num(t) or not 0 <= t <= 1:
            raise BadRequest("temperature: must be a number from 0 to 1", "temperature")
    if body.get("stream"):
        raise BadRequest("stream: streaming is not supported by the scripted server", "stream")
    out = []
    if "system" in body and body["system"] is not None:
        sysp = body["system"]
        if isinstance(sysp, list):
            for j, b in enumerate(sysp):
                if not isinstance(b, dict) or b.get("type") != "text":
                    raise BadRequest(f"system.{j}: system blocks must be text blocks", "system")
        elif not isinstance(sysp, str):
            raise BadRequest("system: must be a string or an array of text blocks", "system")
        chars, _ = _anthropic_blocks(sysp, "system", "system", False) if sysp != "" else (0, 0)
        out.append((_canon({"system": sysp}), math.ceil(chars / 4), _marked(sysp)))
    msgs = body.get("messages")
    if not isinstance(msgs, list) or not msgs:
        raise BadRequest("messages: Field required (a non-empty array)", "messages")
    roles = []
    for i, m in enumerate(msgs):
        p = f"messages.{i}"
        if not isinstance(m, dict):
            raise BadRequest(f"{p}: must be an object", p)
        role = m.get("role")
        if role not in ("user", "assistant"):
            raise BadRequest(f"{p}.role: Input should be 'user' or 'assistant' (got {role!r}); "
                             "put the system prompt in the top-level 'system' field", p)
        if "content" not in m:
            raise BadRequest(f"{p}.content: Field required", p)
        chars, images = _anthropic_blocks(m["content"], f"{p}.content", role, role == "user")
        roles.append(role)
        out.append((_canon({"role": role, "content": m["content"]}),
                    math.ceil(chars / 4) + IMAGE_TOKENS * images, _marked(m["content"])))
    try:
        _check_order(roles, False)
    except BadRequest as e:
        raise BadRequest(e.message.replace("messages[", "messages.").replace("]", ""), e.param)
    return out, roles.count("assistant")


def anthropic_error(status, message, etype=None):
    etype = etype or {400: "invalid_request_error", 404: "not_found_error",
                      429: "rate_limit_error", 500: "api_error"}.get(status, "api_error")
    return {"type": "error", "error": {"type": etype, "message": message}}


# ---------------------------------------------------------------- logging


def redact(body):
    """The request body with base64 image data replaced by its length."""
    b = copy.deepcopy(body)

    def walk(v):
        if isinstance(v, dict):
            src = v.get("source")
            if v.get("type") == "image" and isinstance(src, dict) and isinstance(src.get("data"), str):
                src["data"] = len(src["data"])
            iu = v.get("image_url")
            if isinstance(iu, dict) and isinstance(iu.get("url"), str) and iu["url"].startswith("data:"):
                head, _, data = iu["url"].partition(",")
                iu["url"] = f"{head},<len={len(data)}>"
            for x in v.values():
                walk(x)
        elif isinstance(v, list):
            for x in v:
                walk(x)

    walk(b)
    return b


# ---------------------------------------------------------------- server


class State:
    def __init__(self, responses, model, log_dir):
        self.responses = responses
        self.model = model
        self.log_dir = log_dir
        self.lock = threading.Lock()
        self.counter = 0
        self.fault_seen = set()          # "once" modes already triggered
        self.previous = {}               # api -> canonical messages of the last good request

    def next_id(self):
        with self.lock:
            self.counter += 1
            return self.counter

    def first_time(self, mode):
        with self.lock:
            if mode in self.fault_seen:
                return False
            self.fault_seen.add(mode)
            return True

    def cached_prefix(self, api, msgs):
        """Tokens of the prefix a provider's cache would serve; remembers this request.

        OpenAI-compatible servers cache by themselves: the longest prefix of whole messages equal
        to the previous request's. Anthropic caches only what a ``cache_control`` mark closed: the
        longest equal prefix that ends at an entry (system prompt or message) the previous
        request marked, read only when this request marks an entry at or after it."""
        with self.lock:
            prev = self.previous.get(api, [])
            self.previous[api] = msgs
        n = 0
        while n < len(msgs) and n < len(prev) and msgs[n][0] == prev[n][0]:
            n += 1
        if api == "anthropic":
            last_mark = max((i for i, m in enumerate(msgs) if m[2]), default=-1)
            written = [i for i in range(n) if prev[i][2] and i <= last_mark]
            n = written[-1] + 1 if written else 0
        return sum(m[1] for m in msgs[:n])

    def write_log(self, n, kind, obj):
        if not self.log_dir:
            return
        path = os.path.join(self.log_dir, f"{kind}-{n:03d}.json")
        with open(path, "w") as f:
            json.dump(obj, f, indent=1)
            f.write("\n")


class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "scripted-llm/1.0"
    state: State = None

    def log_message(self, fmt, *args):
        sys.stderr.write("scripted-llm: %s %s\n" % (self.address_string(), fmt % args))

    # ---- plumbing

    def _read_body(self):
        te = self.headers.get("Transfer-Encoding", "").lower()
        if "chunked" in te:
            parts, total = [], 0
            while True:
                line = self.rfile.readline(65537)
                size = int(line.split(b";")[0].strip() or b"0", 16)
                if size == 0:
                    while self.rfile.readline(65537) not in (b"\r\n", b"\n", b""):
                        pass
                    break
                total += size
                if total > MAX_BODY:
                    raise BadRequest("request body too large")
                parts.append(self.rfile.read(size))
                self.rfile.readline(3)
            return b"".join(parts)
        n = int(self.headers.get("Content-Length") or 0)
        if n > MAX_BODY:
            self.close_connection = True
            raise BadRequest("request body too large")
        return self.rfile.read(n) if n > 0 else b""

    def _send(self, status, payload, n, content_type="application/json", extra=None, log=None):
        data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        try:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(data)))
            for k, v in (extra or {}).items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(data)
            self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError):
            self.close_connection = True
        self.state.write_log(n, "response", payload if log is None else log)

    # ---- routes

    def do_GET(self):
        n = self.state.next_id()
        path = self.path.split("?")[0]
        if path.endswith("/v1/models"):
            self._send(200, {"object": "list", "data": [
                {"id": self.state.model, "object": "model", "created": 0, "owned_by": "scripted"}]}, n)
        else:
            self._send(404, openai_error(404, f"Unknown request URL: GET {path}", code="unknown_url"), n)

    def do_POST(self):
        n = self.state.next_id()
        path = self.path.split("?")[0]
        mode = None
        if path.startswith("/fault/"):
            mode, _, rest = path[len("/fault/"):].partition("/")
            path = "/" + rest
        api = "openai" if path.endswith(OPENAI_PATH) else "anthropic" if path.endswith(ANTHROPIC_PATH) else None
        err = openai_error if api != "anthropic" else anthropic_error

        try:
            raw = self._read_body()
        except (BadRequest, ValueError) as e:
            self.close_connection = True
            return self._send(400, err(400, f"could not read the request body: {e}"), n)
        try:
            body = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant) if raw else None
            self.state.write_log(n, "request", redact(body))
        except ValueError as e:  # also UnicodeDecodeError, JSONDecodeError
            body = e
            self.state.write_log(n, "request", {"invalid_json": raw[:4096].decode("utf-8", "replace")})

        if api is None or path not in (OPENAI_PATH, ANTHROPIC_PATH) or (mode is not None and mode not in FAULTS):
            what = f"unknown fault mode {mode!r} (known: {', '.join(FAULTS)})" if mode not in (None, *FAULTS) \
                else f"Unknown request URL: POST {self.path}"
            return self._send(404, openai_error(404, what, code="unknown_url") if api != "anthropic"
                              else anthropic_error(404, what), n)

        # ---- fault modes
        if mode in ("429once", "500once") and self.state.first_time(mode):
            status = 429 if mode == "429once" else 500
            msg = ("Rate limit reached (scripted 429once fault); retry after 0 s" if status == 429
                   else "The server had an error while processing your request (scripted 500once fault)")
            payload = (openai_error(status, msg, code="rate_limit_exceeded" if status == 429 else None)
                       if api == "openai" else anthropic_error(status, msg))
            return self._send(status, payload, n, extra={"Retry-After": "0"})
        if mode == "malformed":
            return self._send(200, b'{"choices": [', n, log={"fault": "malformed", "status": 200,
                                                             "body_text": '{"choices": ['})
        if mode == "nojson":
            html = (b"<!DOCTYPE html>\n<html><head><title>502 Bad Gateway</title></head>\n"
                    b"<body><h1>Bad Gateway</h1><p>scripted nojson fault</p></body></html>\n")
            return self._send(200, html, n, content_type="text/html; charset=utf-8",
                              log={"fault": "nojson", "status": 200, "body_text": html.decode()})
        if mode == "endless":
            return self._endless(n)
        if mode == "slow":
            time.sleep(SLOW_S)

        # ---- a normal answer
        if isinstance(body, Exception):
            return self._send(400, err(400, f"the request body is not valid JSON: {body}"), n)
        try:
            if api == "openai":
                msgs, k = validate_openai(self.headers, body)
            else:
                msgs, k = validate_anthropic(self.headers, body)
        except BadRequest as e:
            if api == "openai":
                payload = openai_error(400, e.message, param=e.param, code=e.code)
            else:
                payload = anthropic_error(400, e.message, "authentication_error"
                                          if e.code == "authentication_error" else None)
            return self._send(400, payload, n)

        text = self.state.responses[k] if k < len(self.state.responses) else EXHAUSTED
        if mode == "cutoff":
            text = text[: len(text) // 2]
        prompt = sum(m[1] for m in msgs)
        cached = self.state.cached_prefix(api, msgs)
        completion = _text_tokens(text)
        no_cache = self.headers.get("x-scripted-no-usage-cache", "").strip() == "1" or mode == "nocache"
        if api == "openai":
            usage = {"prompt_tokens": prompt, "completion_tokens": completion,
                     "total_tokens": prompt + completion}
            if not no_cache:
                usage["prompt_tokens_details"] = {"cached_tokens": cached}
                usage["completion_tokens_details"] = {"reasoning_tokens": 0}
            payload = {"id": f"chatcmpl-scripted-{n:06d}", "object": "chat.completion",
                       "created": int(time.time()), "model": body["model"],
                       "choices": [{"index": 0, "message": {"role": "assistant", "content": text},
                                    "finish_reason": "length" if mode == "cutoff" else "stop"}],
                       "usage": usage}
        else:
            if no_cache:
                usage = {"input_tokens": prompt, "output_tokens": completion}
            else:
                usage = {"input_tokens": prompt - cached, "output_tokens": completion,
                         "cache_read_input_tokens": cached, "cache_creation_input_tokens": 0}
            payload = {"id": f"msg_scripted_{n:06d}", "type": "message", "role": "assistant",
                       "model": body["model"], "content": [{"type": "text", "text": text}],
                       "stop_reason": "max_tokens" if mode == "cutoff" else "end_turn", "stop_sequence": None,
                       "usage": usage}
        self._send(200, payload, n)

    def _endless(self, n):
        sent = 0
        self.close_connection = True
        try:
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Transfer-Encoding", "chunked")
            self.end_headers()
            head = b"%x\r\n" % len(ENDLESS_CHUNK)
            while True:
                self.wfile.write(head + ENDLESS_CHUNK + b"\r\n")
                self.wfile.flush()
                sent += len(ENDLESS_CHUNK)
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass
        self.state.write_log(n, "response", {"fault": "endless", "status": 200, "bytes_sent": sent})


def load_responses(path):
    """The answers of a conversation file or of a cassette, in turn order; exits with the reason."""
    with open(path) as f:
        text = f.read()
    first = text.split("\n", 1)[0]
    try:
        head = json.loads(first)
    except ValueError:
        head = None
    if not (isinstance(head, dict) and "r2g_cassette" in head):
        script = json.loads(text)
        responses = script.get("responses") if isinstance(script, dict) else None
        if not isinstance(responses, list) or not all(isinstance(r, str) for r in responses):
            sys.exit(f"{path}: expected an object with 'responses': [str, ...] or a cassette")
        return responses, script.get("model", "scripted")
    by_turn = {}
    for n, line in enumerate(text.splitlines()[1:], start=2):
        try:
            entry = json.loads(line)
            turn = sum(1 for m in entry["request"]["messages"] if m["role"] == "assistant")
            answer = entry["response"]["text"]
        except (ValueError, KeyError, TypeError) as e:
            sys.exit(f"{path}, line {n}: not a cassette entry ({e!r})")
        if not isinstance(answer, str):
            sys.exit(f"{path}, line {n}: the response text is not a string")
        by_turn.setdefault(turn, answer)
    missing = [k for k in range(len(by_turn)) if k not in by_turn]
    if missing:
        sys.exit(f"{path}: no recorded answer for turn {missing[0]} (a cassette of several conversations?)")
    return [by_turn[k] for k in range(len(by_turn))], head.get("endpoint", {}).get("model", "scripted")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--script", required=True, help="recorded conversation JSON with 'responses', or a cassette")
    ap.add_argument("--port", type=int, default=0, help="TCP port on 127.0.0.1 (0: any free port)")
    ap.add_argument("--log", help="folder for request-NNN.json / response-NNN.json")
    a = ap.parse_args()

    responses, model = load_responses(a.script)
    if a.log:
        os.makedirs(a.log, exist_ok=True)

    Handler.state = State(responses, model, a.log)
    server = ThreadingHTTPServer(("127.0.0.1", a.port), Handler)
    server.daemon_threads = True
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    t = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
    t.start()
    print(f"LISTENING {server.server_address[1]}", flush=True)
    while not stop.wait(0.2):
        pass
    server.shutdown()
    server.server_close()


if __name__ == "__main__":
    main()
