"""run.json's library versions: installed distributions read once per process, the imported-module fallback not."""

import sys
import types
from importlib.metadata import version

from roadview_noise import manifest


def test_versions_are_the_installed_distributions():
    got = manifest.library_versions()
    assert got["scipy"] == version("scipy")
    assert got["numpy"] == version("numpy")
    got["scipy"] = "changed by a caller"
    assert manifest.library_versions()["scipy"] == version("scipy")     # each call returns its own record


def test_a_library_without_distribution_falls_back_to_the_imported_module(monkeypatch):
    monkeypatch.setitem(manifest._VERSIONED, "rvnoise_fake_lib", ("rvnoise-fake-dist",))
    assert manifest.library_versions()["rvnoise_fake_lib"] == "unavailable"
    monkeypatch.setitem(sys.modules, "rvnoise_fake_lib", types.SimpleNamespace(__version__="9.9"))
    assert manifest.library_versions()["rvnoise_fake_lib"] == "9.9"      # the cached look-up found no distribution


def test_model_warnings_are_listed_in_the_order_of_their_texts():
    """run.json's warnings do not depend on the order files finished in or on Python's string hashing (a set's
    order; twenty texts make an accidental pass of the old order improbable: 1 in 20!)."""
    from roadview_noise import runner

    texts = [f"model warning {chr(ord('t') - i)}{i}" for i in range(20)]
    tally = runner._Tally(runner.RunSummary())
    tally.add({"status": "ok", "warnings": texts[10:] + [f"{texts[0]} (×3)"]})
    tally.add({"status": "ok", "warnings": texts[:10][::-1]})
    lines = tally.warnings()
    assert lines == [f"{t} ({2 if t == texts[0] else 1} file{'s' if t == texts[0] else ''}; in the manifest)"
                     for t in sorted(texts)]
