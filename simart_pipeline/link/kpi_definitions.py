"""Texts of the ``kpis`` store: references, what NaN means, and the definitions of the numeric
variables that :func:`.kpis.compute_kpis` does not define inline (every KPI: docs/link-level.md)."""

REFERENCES = (
    "3GPP TS 38.211 4.2-4.3 (numerology, slots); TS 38.214 5.1.3.1 (MCS tables), 5.1.3.2 (TBS); "
    "TS 38.212 5.2.2, 7.2.2 (code-block segmentation, LDPC base graph); EESM: Brueninger et al., "
    "PIMRC 2005 and 3GPP TR 25.892 Annex A; OLLA: Pedersen et al., VTC 2007-Fall; BLER tables "
    "and EESM beta values: Sionna SYS 2.2 (Apache-2.0); definitions: docs/link-level.md")

NAN_LINK = ("link_kpis_valid is false (no valid path, or the receiver is inside a building or "
            "within 1 cm of the transmitter), or a linear value of exactly 0")
NAN_RX = ("rx_served is false (no valid path to any base station, or the receiver's KPIs are "
          "masked: rx_inside_building or rx_near_tx), or a linear value of exactly 0")
NAN_RATE = ("the receiver's KPIs are masked (rx_inside_building or rx_near_tx); the value is 0 "
            "where the receiver has no valid path to any base station")
NAN_INTERFERENCE = NAN_RX + "; or no other base station reaches the receiver (no interference)"

DEFINITIONS = {
    "best_beam": "argmax over beams of beam_sinr_db (ties: lowest index)",
    "best_beam_gain_db": "beam_gain_db at best_beam",
    "best_beam_sinr_db": "beam_sinr_db at best_beam",
    "serving_link": "argmax over the receiver's candidate links of best_beam_sinr_db (ties: "
                    "lowest link)",
    "serving_beam": "best_beam of the serving link",
    "signal_power_per_re_dbm": "10 log10(mean_k S[k] / 1 mW), S[k] = p |y[k]|^2 after MRC",
    "interference_power_per_re_dbm": "10 log10(mean_k I[k] / 1 mW), I per interference_rule",
    "mcs_index": "inner loop: highest MCS with TBLER <= bler_target at its own EESM, else the "
                 "lowest MCS with a BLER curve; outer loop: the same on the last effective SINR "
                 "report minus olla_offset_db",
    "modulation_order": "Q_m of mcs_index (TS 38.214 Table 5.1.3.1)",
    "code_rate": "R = (R x 1024) / 1024 of mcs_index (TS 38.214 Table 5.1.3.1)",
    "tbs_bits": "TS 38.214 5.1.3.2 with N_RE = num_re_for_tbs, R and Q_m of mcs_index, 1 layer",
    "num_code_blocks": "C of TS 38.212 5.2.2",
    "code_block_size_bits": "K' = (TBS + L_TB) / C + L, TS 38.212 5.2.2",
    "ldpc_base_graph": "TS 38.212 7.2.2: 2 if TBS <= 292, or TBS <= 3824 and R <= 0.67, or "
                       "R <= 0.25; else 1",
    "olla_offset_db": "+ olla_delta_up_db after a NACK, - olla_delta_down_db after an ACK, "
                      "clipped to olla_offset_limits_db",
    "mcs_modulation_order": "TS 38.214 Table 5.1.3.1 (attr mcs_table)",
    "mcs_code_rate": "TS 38.214 Table 5.1.3.1 (attr mcs_table)",
    "mcs_eesm_beta": "EESM beta table of Sionna SYS 2.2 (simart_pipeline/link/data)",
    "mcs_tbs_bits": "TS 38.214 5.1.3.2 with N_RE = num_re_for_tbs, 1 layer",
}
