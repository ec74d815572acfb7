"""derive_rng is part of the output contract: a recipe's outputs (and every manifest's reproduction) depend on the
exact generator it returns for (seed, keys). These values were drawn by the code of round 10; a change of the
derivation (hash, word order, seeding) fails here before it changes anyone's outputs."""

from roadview_noise.seeding import derive_rng


def test_derived_generators_are_those_of_earlier_releases():
    frame = derive_rng(20261122, "radar/seq0/000001.pcd", 0, "rain.radar")
    sequence = derive_rng(0, "sequence", "radar/seq0", "occlusion.radar")
    assert [int(x) for x in frame.integers(1 << 62, size=3)] == [3547665550919116950, 1428865741040324995,
                                                                   1407695426225495295]
    assert [int(x) for x in sequence.integers(1 << 62, size=3)] == [2344125008539115350, 2134640832687380856,
                                                                      4429029162904212249]
