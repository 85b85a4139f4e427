//! `nimbus mitsuba`: a scene's cloud, sun and camera as a Mitsuba 3 scene.

use crate::scene::SceneFile;
use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct MitsubaArgs {
    /// Scene file (TOML).
    pub scene: PathBuf,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Samples per pixel written into the XML.
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
}

/// Writes OUT/cloud.vol and OUT/scene.xml.
pub fn mitsuba(args: MitsubaArgs) -> Result<()> {
    let file = SceneFile::load(&args.scene)?;
    let scene = file.build_scene(None)?;
    crate::mitsuba::export(&scene, args.spp, &args.out)?;
    println!("wrote {}/cloud.vol and {}/scene.xml", args.out.display(), args.out.display());
    Ok(())
}
