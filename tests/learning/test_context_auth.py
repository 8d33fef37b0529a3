"""Who vouches for a Zenoh context (issue 36): the adapter key's MAC over machine, run and sequence, or the ACL.

The test vector and the reference signer are read from docs/zenoh.md ("Signed context"), so the doc an
adapter's author follows is what the daemon accepts; everything else here signs with that signer too.
"""

from __future__ import annotations

import hashlib
import hmac
import json

import pytest

from millsense.daemon.learning.context import ContextTrack, ctx_from_daq
from millsense.daemon.learning.context_auth import UNTRUSTED, ContextAuth, mac_hex, message, untrusted_reason
from millsense.drivers.protocol import Context
from tests.learning.doc_signer import signer, vector

pytestmark = pytest.mark.quick

KEY = "adapter-key-of-at-least-32-characters-0123456789"
MACHINE, RUN = "mch10-01", "0123456789abcdef"
CTX = {"program": 1234, "tool": 12, "operation": 3, "afc_allowed": True}


def signed(seq: int, *, key: str = KEY, machine: str = MACHINE, run_id: str = RUN, **over) -> dict:
    return json.loads(signer()(key, machine, run_id, seq, {**CTX, **over}))


def track(key: str = KEY, trust: str = "none") -> ContextTrack:
    t = ContextTrack("zenoh")
    t.auth = ContextAuth(MACHINE, RUN, key, trust)
    return t


def test_the_docs_test_vector_is_what_the_daemon_computes_and_accepts():
    v = vector()
    flags = {"cycle": True, "monitor": True, "afc_allowed": v["context"]["afc_allowed"], "feed_held": False}
    msg = message(v["machine"], v["run_id"], v["seq"], v["context"]["program"], v["context"]["tool"],
                  v["context"]["operation"], flags)
    assert msg == v["message"]
    assert mac_hex(v["key"], msg) == v["mac"]
    # independent of the daemon's code: the standard library on the doc's MAC input
    assert hmac.new(v["key"].encode(), v["message"], hashlib.sha256).hexdigest() == v["mac"]
    # the doc's reference signer makes that MAC, and the daemon takes its payload as vouched for
    payload = json.loads(signer()(v["key"], v["machine"], v["run_id"], v["seq"], v["context"]))
    assert payload["mac"] == v["mac"]
    auth = ContextAuth(v["machine"], v["run_id"], v["key"])
    assert auth.judge(payload, {**v["context"], **flags}) == ("mac", None)


def test_a_signed_context_is_vouched_for_and_its_sequence_spent_once():
    t = track()
    payload = signed(1)
    judged = t.judge_zenoh(payload)
    assert judged.authority == "mac" and judged.trusted
    assert t.auth.last_seq == 0          # judging spends nothing: the Zenoh thread asks first
    assert t.on_zenoh(payload, 10) is None
    assert t.at(10).authority == "mac" and t.auth.last_seq == 1
    again = t.on_zenoh(payload, 20)       # the same put replayed
    assert again is not None and "seq 1 is not above 1" in again
    assert t.on_zenoh(signed(5), 30) is None   # numbers may skip; they only rise
    refused = t.on_zenoh(signed(3), 40)
    assert refused is not None and "not above 5" in refused
    assert t.at(40).authority == "mac" and t.at(40).tool == 12


@pytest.mark.parametrize("change, why", [
    (lambda p: {**p, "tool": 7}, "does not verify"),                 # a field changed after signing
    (lambda p: {**p, "afc_allowed": False}, "does not verify"),
    (lambda p: {**p, "cycle": False}, "does not verify"),            # a flag left out is signed as its default
    (lambda p: {**p, "mac": "0" * 64}, "does not verify"),
    (lambda p: {**p, "mac": p["mac"].upper()}, "64 lowercase hex"),
    (lambda p: {**p, "seq": 2}, "does not verify"),                  # the sequence is signed
    (lambda p: {**p, "seq": True}, "seq must be"),
    (lambda p: {**p, "seq": 0}, "seq must be"),
    (lambda p: {**p, "run_id": "fedcba9876543210"}, "signed for run fedcba9876543210"),
    (lambda p: {k: v for k, v in p.items() if k != "mac"}, "without mac"),
])
def test_a_tampered_signed_context_is_refused_whole(change, why):
    t = track()
    refused = t.on_zenoh(change(signed(1)), 10)
    assert refused is not None and why in refused, refused
    assert t.at(10) is None and t.auth.last_seq == 0   # refused, not taken as an unsigned label either


@pytest.mark.parametrize("who", [dict(machine="mch10-02"), dict(key="another-key-of-at-least-32-characters-0000"),
                                 dict(run_id="fedcba9876543210")])
def test_signed_for_another_machine_key_or_run_is_refused(who):
    t = track()
    judged = t.judge_zenoh(signed(1, **who))
    assert isinstance(judged, str) and judged.startswith("context refused"), judged
    assert t.on_zenoh(signed(1), 10) is None   # the right one still goes through


def test_unsigned_labels_the_cut_but_is_not_vouched_for():
    t = track()
    assert t.on_zenoh(dict(CTX), 10) is None
    ctx = t.at(10)
    assert (ctx.tool, ctx.afc_allowed, ctx.authority, ctx.trusted) == (12, True, "none", False)
    assert untrusted_reason(ctx) == UNTRUSTED
    # an unsigned put after a signed one with the same fields is news: AFC stops following
    assert t.on_zenoh(signed(1), 20) is None and t.at(20).trusted
    assert t.on_zenoh(dict(CTX), 30) is None and not t.at(30).trusted


def test_trust_acl_vouches_for_unsigned_puts_but_not_for_a_bad_signature():
    t = track(key="", trust="acl")
    assert t.on_zenoh(dict(CTX), 10) is None and t.at(10).authority == "acl" and t.at(10).trusted
    t = track(trust="acl")
    assert t.on_zenoh(dict(CTX), 10) is None and t.at(10).authority == "acl"
    refused = t.on_zenoh({**signed(1), "tool": 7}, 20)
    assert refused is not None and "does not verify" in refused


def test_without_a_key_a_signature_cannot_be_checked_and_counts_for_nothing():
    t = track(key="")
    assert t.on_zenoh(signed(1), 10) is None
    assert t.at(10).authority == "none" and not t.at(10).trusted
    # a track with no judge at all (replay): nobody vouches either
    bare = ContextTrack("zenoh")
    assert bare.on_zenoh(signed(1), 10) is None and not bare.at(10).trusted


def test_the_daqs_own_context_is_trusted_and_no_context_is_the_configs_call():
    ctx = ctx_from_daq(Context(0, 1, 2, 3, 0x07))
    assert ctx.authority == "daq" and ctx.trusted and untrusted_reason(ctx) is None
    assert untrusted_reason(None) is None


def test_an_unknown_trust_is_refused():
    with pytest.raises(ValueError):
        ContextAuth(MACHINE, RUN, KEY, "everyone")
