"""Passwords never shown: storage URLs and any text (an exception message) with every credential masked."""
from __future__ import annotations

import re

# -- credentials ----------------------------------------------------------------------------------
#
# A URL is masked by SQLAlchemy's own rendering (``make_url(url).render_as_string(hide_password=True)``)
# plus the query parameters that carry secrets (libpq reads ``?password=``, ``?sslpassword=``, ``?passfile=``,
# ``?sslkey=``; MySQL drivers ``?passwd=``, ``?ssl_key=``). A regex is used only where SQLAlchemy cannot
# parse the string (it raises ArgumentError / ValueError, e.g. ``u:a@b:c@host:5432`` where it reads
# ``c@host:5432`` as the port) and for free text such as an exception message that may embed a URL or
# a libpq DSN (``host=... password=...``): there is no structure to parse, so every ``scheme://user:...@``
# userinfo (up to the last ``@`` of the token) and every ``secret-ish-key=value`` is masked.

MASK = "***"


#: query / DSN keys whose value is a secret (a password, a key, a file of passwords, a token)
SECRET_KEY_RE = re.compile(r"pass|pwd|secret|token|key|auth|cred", re.I)


_URL_PW_RE = re.compile(r"(?P<pre>\b[A-Za-z][A-Za-z0-9+.\-]*://[^\s:/@]*:)(?P<pw>\S*)@(?P<post>[^\s@]*)")


#: in free text only the key names drivers actually use, so that e.g. "--fix monkey=3" stays readable
_KV_RE = re.compile(r"(?<![A-Za-z0-9_.\-])(?P<k>password|passwd|pwd|pass|sslpassword|passfile|sslkey|ssl_key|secret|"
                    r"token|access_token|api_key|apikey|auth_token|PGPASSWORD)(?P<eq>\s*=\s*)"
                    r"(?P<v>'(?:[^'\\]|\\.)*'|\"[^\"]*\"|[^\s&'\",;)\]]+)", re.I)


#: the start of a URL that lost its "//" or ":" (``postgresql:/u:pw@h``, ``postgresql//u:pw@h``, ``postgresql:u:pw@h``)
_LOOSE_PREFIX_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*(?::/*|/+)")


def _loose_password_span(s: str) -> tuple[int, int] | None:
    """Where the password of a malformed URL without ``://`` is: ``(start, end)`` in ``s``, or None.

    ``postgresql:/user:pw@host/db``, ``postgresql//user:pw@host/db``, ``postgresql:user:pw@host/db`` and
    ``user:pw@host/db`` are typos of a URL whose userinfo still carries the password: everything from the first
    ``:`` of the userinfo to the last ``@`` is masked (an ``@`` in a password is not always encoded). A
    journal path or a plain path (no ``:`` before its last ``@``) has none."""
    if s.startswith("journal:") or "@" not in s:
        return None
    at = s.rfind("@")
    head = s[:at]
    start = 0
    m = _LOOSE_PREFIX_RE.match(head)
    if m and (":" in head[m.end():] or "/" in m.group(0)):  # a scheme before the userinfo ("user:" alone is none)
        start = m.end()
    colon = head.find(":", start)
    if colon < 0 or colon + 1 >= at or head[colon + 1:] in ("PASS", "PASSWORD", MASK):
        return None
    return colon + 1, at


def _loose_mask(s: str) -> str:
    """A malformed URL without ``://`` with its password (:func:`_loose_password_span`) and secret query
    parameters masked; other strings unchanged."""
    span = _loose_password_span(s)
    if span is None:
        return s
    return _mask_query(s[:span[0]] + MASK + s[span[1]:])


def _regex_mask(text: str) -> str:
    """Fallback for text SQLAlchemy cannot parse: URL userinfo passwords and secret key=value pairs."""
    text = _URL_PW_RE.sub(lambda m: m.group(0) if m.group("pw") in ("PASS", "PASSWORD", MASK)  # placeholders
                          else m.group("pre") + MASK + "@" + m.group("post"), text)
    return _KV_RE.sub(lambda m: m.group(0) if m.group("v").startswith(MASK) else m.group("k") + m.group("eq") + MASK,
                      text)


def _repair_at(url: str) -> str:
    """``scheme://user:pa@ss@host/db`` -> ``scheme://user:pa%40ss@host/db``.

    SQLAlchemy (like libpq) ends the password at the first ``@``, so an unencoded ``@`` in a password
    makes ``ss@host`` the host name and ``ss`` leaks in every message naming the host. A host name cannot
    contain ``@``: where SQLAlchemy's host does, everything up to its last ``@`` belongs to the password
    (or, with no password, to the user name), which is then percent-encoded. Where SQLAlchemy cannot
    parse the URL at all (e.g. ``u:a@b:c@host:5432``: it reads ``c@host:5432`` as the port), the userinfo
    is taken to run to the last ``@`` of the URL, as ``urllib.parse`` does. URLs with at most one ``@``,
    or whose other ``@`` is elsewhere (a path, a query value), are returned unchanged."""
    from urllib.parse import quote, unquote
    scheme, sep, rest = url.partition("://")
    if not sep or rest.startswith("/") or rest.count("@") < 2:
        return url
    from sqlalchemy.engine import make_url
    try:
        u = make_url(url)
    except Exception:  # noqa: BLE001 - ArgumentError, ValueError (a port that is no number): see below
        u = None
    if u is not None:
        if not u.host or "@" not in u.host:
            return url
        extra, host = u.host.rsplit("@", 1)
        if u.password is not None:
            u = u.set(password=f"{u.password}@{extra}", host=host)
        else:
            u = u.set(username=f"{u.username or ''}@{extra}", host=host)
        return u.render_as_string(hide_password=False)
    at = rest.rfind("@")
    userinfo, after = rest[:at], rest[at + 1:]
    user, colon, pw = userinfo.partition(":")
    if not colon:
        user, pw = userinfo, None
    enc = lambda v: quote(unquote(v), safe="")  # noqa: E731 - idempotent on already-encoded parts
    cred = enc(user) + (":" + enc(pw) if pw is not None else "")
    return f"{scheme}://{cred}@{after}"


def _parse(url: str):
    """SQLAlchemy's URL object for ``url`` (after :func:`_repair_at`), or None if it cannot parse it."""
    from sqlalchemy.engine import make_url
    try:
        return make_url(_repair_at(url))
    except Exception:  # noqa: BLE001 - ArgumentError, ValueError (bad port), ...: not parseable
        return None


def _mask_query(rendered: str) -> str:
    base, q, query = rendered.partition("?")
    if not q:
        return rendered
    from urllib.parse import unquote_plus
    parts = []
    for item in query.split("&"):
        k, eq, _v = item.partition("=")
        parts.append(f"{k}={MASK}" if eq and SECRET_KEY_RE.search(unquote_plus(k)) else item)
    return base + "?" + "&".join(parts)


def mask_url(url: str | None) -> str:
    """The storage URL as shown to users: password and secret query parameters replaced by ``***``.

    Journal files and bare paths (no ``://``) are returned unchanged. Malformed URLs are masked too."""
    if url is None:
        return ""
    s = str(url).strip()
    if "://" not in s:
        return _loose_mask(s)
    u = _parse(s)
    if u is None:
        return _regex_mask(s)
    return _mask_query(u.render_as_string(hide_password=True))


def _secrets(url: str | None) -> list[str]:
    """Every secret value the URL carries, raw and in its percent-encoded forms (longest first)."""
    if not url:
        return []
    from urllib.parse import quote, quote_plus
    s = str(url).strip()
    vals = []
    if "://" not in s:  # a malformed URL (a typo of one) still carries its password
        span = _loose_password_span(s)
        if span is not None:
            vals.append(s[span[0]:span[1]])
    elif (u := _parse(s)) is not None:
        if u.password:
            vals.append(str(u.password))
        for k, v in u.query.items():
            if SECRET_KEY_RE.search(k):
                vals.extend([v] if isinstance(v, str) else list(v))
    else:  # unparseable: what the regex would mask
        m = _URL_PW_RE.search(s)
        if m and m.group("pw"):
            vals.append(m.group("pw"))
    out = set()
    for v in vals:
        if v:
            out.update({v, quote(v, safe=""), quote_plus(v), quote(v)})
    return sorted(out, key=len, reverse=True)


def scrub(text, url: str | None = None) -> str:
    """``text`` (e.g. an exception message from SQLAlchemy or psycopg2) as one line, with the secrets of
    ``url`` and any URL password or ``password=...`` pair it embeds replaced by ``***``."""
    text = " ".join(str(text).split())
    for sec in _secrets(url):
        if len(sec) >= 4:
            text = text.replace(sec, MASK)
        else:  # a very short secret: only where it stands alone, not inside every word
            text = re.sub(rf"(?<![A-Za-z0-9]){re.escape(sec)}(?![A-Za-z0-9])", MASK, text)
    return _regex_mask(text)
