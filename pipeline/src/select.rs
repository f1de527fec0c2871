//! The model selection's record in `RESULT.json` and for the console.

use b2b_calib::select::SelectedRun;
use b2b_protocol::ModelSelection;

/// `RESULT.json`'s `model_selection` of a run (`None` when it was not
/// cross-validated).
pub(crate) fn model_selection(selected: &SelectedRun) -> Option<ModelSelection> {
    let s = selected.selection.as_ref()?;
    let held_out = s
        .held_out_px
        .iter()
        .filter_map(|(c, v)| v.map(|v| (c.name(), v)))
        .collect();
    tracing::info!(
        chosen = s.chosen.name(),
        spread_scale = selected.spread_scale,
        fold_scatter = selected.fold_scatter,
        min_training = s.min_training,
        agreeing = selected
            .agreeing
            .iter()
            .map(|c| c.name())
            .collect::<Vec<_>>()
            .join(", "),
        "estimator chosen by {}-fold cross-validation: {}",
        s.folds,
        s.held_out_px
            .iter()
            .map(|(c, v)| match v {
                Some(v) => format!("{} {v:.3} px", c.name()),
                None => format!("{} failed", c.name()),
            })
            .collect::<Vec<_>>()
            .join(", ")
    );
    Some(ModelSelection {
        chosen: s.chosen.name(),
        held_out_px: held_out,
        folds: s.folds,
        spread_scale: selected.spread_scale,
        fold_scatter: selected.fold_scatter,
        agreeing: selected.agreeing.iter().map(|c| c.name()).collect(),
    })
}
