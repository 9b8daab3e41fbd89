"""Materials and light of a trained run (``anisdf materials``): with the reconstructed surface fixed, an environment
light and a glTF metallic-roughness material are fitted to the training photos by differentiable rendering, so that
the reconstruction can be relit (``anisdf relight``) and exported as a standard PBR asset (``anisdf export --pbr``).

Modules: :mod:`.brdf` (GGX, Smith, Schlick; the split-sum tables), :mod:`.environment` (equirectangular HDR maps:
files, lookups, rotation, prefiltering), :mod:`.surface` (the run's surface as a mesh, pixels cast onto it),
:mod:`.shading` (split-sum shading and its brute-force reference), :mod:`.fit` (the optimisation), :mod:`.asset`
(the fitted result on disk and as a glb).
"""
