"""Motion input: parsers (bvh, asfamc) -> SourceMotion (skeleton), bone-name maps (names),
retargeting onto the cmu_mb body (retarget), resampling (resample), the motion descriptor
gamma of thesis eq. 6.17 (descriptor), and the bundled clips (clips)."""
