"""Synthetic CVGL-style stereo data: rendering, rig protocols and HDF5 storage.

Modules (numpy only, no deep-learning backend is imported):

* ``storage``   the HDF5 dataset schema, its reader ``StereoFile``
* ``writer``    ``StereoWriter``: a dataset file written atomically, resumably
* ``textures``  photographic materials from scikit-image, with mip levels
* ``scenes``    the procedural towns ``Town01`` and ``Town02``
* ``render``    a vectorised numpy ray caster (depth = xCam, Eq. 4a)
* ``shading``   the ray caster's materials, sunlight, shadows and haze
* ``protocols`` the ``cvgl``, ``random``, ``cameras`` and ``wild`` stereo-rig
  protocols
* ``pair``      one stereo pair: its two images and its labels
* ``generate``  ``generate_dataset`` and the CLI
  (``python -m cpl_keras.data.generate --pairs N --out data/cvgl.h5``)
* ``preview``   the generator's ``--preview``: a contact sheet of a few pairs
* ``estimate``  what generating a dataset takes on this machine now (disk, time)

See docs/data.md for the conventions and how the data differs from CVGL.
"""
