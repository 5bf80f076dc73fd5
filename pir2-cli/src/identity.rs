//! A candle checkpoint's identity (the policy it was trained as, the SHA-256 of its weights;
//! `identity.json`, see `pir2_backends::checkpoint::Identity`) checked where a command is
//! about to run it: a checkpoint trained as one policy is never run under another policy's
//! schedule, and `pir2 eval --remote` never evaluates a server holding other weights.

use std::path::Path;

use anyhow::{bail, Context, Result};

use pir2_backends::candle::CandleModel;
use pir2_backends::checkpoint::Identity;
use pir2_runtime::Policy;

/// Refuse to run the checkpoint `dir` (loaded as `model`) as `policy` when it was trained as
/// another policy; `how` says where `policy` came from (e.g. `--policy`). A checkpoint whose
/// policy is unrecorded (written before checkpoints recorded it) runs, with a note.
pub fn expect_policy(model: &CandleModel, dir: &Path, policy: Policy, how: &str) -> Result<()> {
    expect_trained_as(model.policy(), dir, policy, how)
}

/// [`expect_policy`] for any checkpoint whose recorded policy is `trained` (`None`:
/// unrecorded), e.g. an ONNX checkpoint ([`crate::onnx_checkpoint`]).
pub fn expect_trained_as(
    trained: Option<Policy>,
    dir: &Path,
    policy: Policy,
    how: &str,
) -> Result<()> {
    match trained {
        Some(trained) if trained != policy => bail!(
            "checkpoint {} was trained as {}; {how} {} would run it under another schedule",
            dir.display(),
            trained.name(),
            policy.name()
        ),
        Some(_) => Ok(()),
        None => {
            eprintln!(
                "note: checkpoint {} has no recorded policy (unrecorded: written before \
                 checkpoints recorded their identity); running it as {}",
                dir.display(),
                policy.name()
            );
            Ok(())
        }
    }
}

/// The identity a policy server announces for `model` (JSON of [`Identity`]; the weights'
/// hash is that of the checkpoint it was loaded from).
pub fn announce(model: &CandleModel) -> Option<String> {
    let sha = model.weights_sha256()?;
    serde_json::to_string(&Identity {
        policy: model.policy(),
        weights_sha256: sha.to_owned(),
    })
    .ok()
}

/// Check the identity a policy server announced (`None`: a server that announces none)
/// against the local checkpoint `dir` (loaded as `local`) and the `--policy` asked for:
/// other weights or another policy are refused by name.
pub fn expect_server(
    announced: Option<&str>,
    endpoint: &str,
    local: &CandleModel,
    dir: &Path,
    policy: Policy,
) -> Result<()> {
    let Some(text) = announced else {
        eprintln!(
            "note: the policy server at {endpoint} announces no checkpoint identity \
             (unrecorded: an older pir2 or a non-candle model); its weights are unchecked"
        );
        return Ok(());
    };
    let id: Identity = serde_json::from_str(text).with_context(|| {
        format!("the policy server at {endpoint} announced an unreadable identity: {text:?}")
    })?;
    if let Some(trained) = id.policy.filter(|&p| p != policy) {
        bail!(
            "the policy server at {endpoint} runs a checkpoint trained as {}; --policy {} \
             would run it under another schedule",
            trained.name(),
            policy.name()
        );
    }
    if let Some(mine) = local.weights_sha256() {
        if mine != id.weights_sha256 {
            bail!(
                "the policy server at {endpoint} runs other weights than checkpoint {} \
                 (server model.safetensors SHA-256 {}, local {mine}): serve this checkpoint \
                 there, or evaluate the server's checkpoint",
                dir.display(),
                id.weights_sha256
            );
        }
    }
    Ok(())
}
