/* firmware.c: onboard.firmware.Firmware in C (firmware.h). */
#include "firmware.h"

#include <math.h>
#include <string.h>

#include "st_messages.h"

firmware_budget_t firmware_default_budget(void)
{
    firmware_budget_t b;
    b.flops_per_s = 50e6;
    b.min_frame_period_s = 0.1;
    return b;
}

static void restart_estimator(firmware_t *fw)
{
    uint8_t table[BANKS_TABLE_BYTES];
    float values[ST_PARAM_N_FIELDS];
    uint32_t generation;
    uint32_t crc;
    fw->est_running = 0u;
    if (fw->est == NULL || !banks_active_set(&fw->store, &generation, table, &crc)) {
        return;
    }
    fw->est_generation = generation;
    st_param_table_decode(table, values);
    fw->est_running = estimator_seam_start(fw->est, &fw->est_config, values) == 0 ? 1u : 0u;
}

int firmware_init(firmware_t *fw, const banks_store_t *store, estimator_seam_state_t *est,
                  const estimator_seam_config_t *config, const firmware_budget_t *budget)
{
    memset(fw, 0, sizeof *fw);
    if (!(isfinite(budget->flops_per_s) && budget->flops_per_s > 0.0)) {
        return 1;
    }
    if (!(isfinite(budget->min_frame_period_s) && budget->min_frame_period_s > 0.0)) {
        return 1;
    }
    fw->store = *store;
    fw->budget = *budget;
    fw->est = estimator_seam_available() ? est : NULL;
    if (config != NULL) {
        fw->est_config = *config;
    }
    restart_estimator(fw);
    return 0;
}

/* ------------------------------------------------------------------------------------------------ replies */
/* Each reply is built in its own message struct and encoded by its own encoder (st_encode_<name>), never through
 * st_message_t, whose union holds a 255-star frame (3.6 kB): a reply costs its own bytes of stack. */
static int put_reply(size_t n, size_t *reply_len)
{
    *reply_len = n;
    return n == 0u ? FIRMWARE_NO_SPACE : FIRMWARE_REPLY;
}

static int ack(uint16_t tag, uint8_t command, uint32_t value, uint8_t *reply, size_t cap, size_t *reply_len)
{
    st_ack_t m;
    memset(&m, 0, sizeof m);
    m.tag = tag;
    m.command = command;
    m.value = value;
    return put_reply(st_encode_ack(&m, reply, cap), reply_len);
}

static int nak_text(uint16_t tag, uint8_t command, uint8_t code, const pyformat_text_t *text, uint8_t *reply,
                    size_t cap, size_t *reply_len)
{
    st_nak_t m;
    memset(&m, 0, sizeof m);
    m.tag = tag;
    m.command = command;
    m.code = code;
    m.text_bytes = (uint8_t)text->len;
    memcpy(m.text, text->buf, text->len);
    return put_reply(st_encode_nak(&m, reply, cap), reply_len);
}

static int nak(uint16_t tag, uint8_t command, uint8_t code, const char *text, uint8_t *reply, size_t cap,
               size_t *reply_len)
{
    pyformat_text_t t;
    pyformat_init(&t);
    pyformat_str(&t, text);
    return nak_text(tag, command, code, &t, reply, cap, reply_len);
}

/* a banks result -> Ack(value) or Nak(refusal) or the power cut */
static int ack_or_nak(int result, uint16_t tag, uint8_t command, uint32_t value, const banks_refusal_t *refusal,
                      uint8_t *reply, size_t cap, size_t *reply_len)
{
    if (result == BANKS_POWER_CUT) {
        return FIRMWARE_POWER_CUT;
    }
    if (result == BANKS_REFUSED) {
        return nak_text(tag, command, refusal->code, &refusal->text, reply, cap, reply_len);
    }
    return ack(tag, command, value, reply, cap, reply_len);
}

static int param_table(uint16_t tag, uint8_t bank, uint32_t generation, uint32_t crc, const uint8_t *table,
                       uint8_t *reply, size_t cap, size_t *reply_len)
{
    st_param_table_t m;
    memset(&m, 0, sizeof m);
    m.tag = tag;
    m.bank = bank;
    m.generation = generation;
    m.crc32 = crc;
    memcpy(m.table, table, BANKS_TABLE_BYTES);
    return put_reply(st_encode_param_table(&m, reply, cap), reply_len);
}

static uint32_t estimator_updates(const firmware_t *fw)
{
    float values[ESTIMATOR_SEAM_N_PARAMS];
    float sigma[ESTIMATOR_SEAM_N_PARAMS];
    uint32_t mask;
    uint32_t n_updates;
    if (!fw->est_running) {
        return 0u;
    }
    estimator_seam_estimate(fw->est, values, sigma, &mask, &n_updates);
    return n_updates;
}

static int status(const firmware_t *fw, uint16_t tag, uint8_t *reply, size_t cap, size_t *reply_len)
{
    st_telemetry_t m;
    uint8_t table[BANKS_TABLE_BYTES];
    uint32_t generation = 0u;
    uint32_t crc = 0u;
    memset(&m, 0, sizeof m);
    if (!banks_active_set(&fw->store, &generation, table, &crc)) {
        generation = 0u;
        crc = 0u;
    }
    m.tag = tag;
    m.streaming = fw->streaming;
    m.stage_state = fw->store.stage_state;
    m.active_generation = generation;
    m.active_crc32 = crc;
    m.frames_processed = fw->counters.frames_processed;
    m.last_frame = fw->counters.last_frame;
    m.estimator_updates = estimator_updates(fw);
    return put_reply(st_encode_telemetry(&m, reply, cap), reply_len);
}

static int read_estimate(const firmware_t *fw, uint16_t tag, uint8_t *reply, size_t cap, size_t *reply_len)
{
    const uint8_t cmd = ST_MSG_READ_ESTIMATE;
    st_estimate_t m;
    uint32_t mask;
    uint32_t n_updates;
    if (fw->est == NULL) {
        return nak(tag, cmd, ST_NAK_NO_ESTIMATE, "this sensor has no onboard estimator", reply, cap, reply_len);
    }
    if (!fw->est_running) {
        return nak(tag, cmd, ST_NAK_NO_ESTIMATE, "no active parameter set to start from", reply, cap, reply_len);
    }
    memset(&m, 0, sizeof m);
    estimator_seam_estimate(fw->est, m.values, m.sigma, &mask, &n_updates);
    if (n_updates == 0u) {
        return nak(tag, cmd, ST_NAK_NO_ESTIMATE, "the estimator has not processed a frame yet", reply, cap,
                   reply_len);
    }
    m.tag = tag;
    m.status = ST_ESTIMATE_STATUS_RUNNING;
    m.estimated_mask = (uint16_t)mask;
    m.base_generation = fw->est_generation;
    m.n_updates = n_updates;
    m.last_frame = fw->est_last_frame;
    return put_reply(st_encode_estimate(&m, reply, cap), reply_len);
}

/* the Python class name of a message type that is not a command */
static const char *reply_name(uint8_t type)
{
    switch (type) {
    case ST_MSG_ACK: return "Ack";
    case ST_MSG_NAK: return "Nak";
    case ST_MSG_TELEMETRY: return "Telemetry";
    case ST_MSG_PARAM_TABLE: return "ParamTable";
    case ST_MSG_ESTIMATE: return "Estimate";
    case ST_MSG_CENTROID_FRAME: return "CentroidFrame";
    case ST_MSG_END_OF_STREAM: return "EndOfStream";
    default: return "Message";
    }
}

static uint16_t reply_tag(const st_message_t *m)
{
    switch (m->type) {
    case ST_MSG_ACK: return m->u.ack.tag;
    case ST_MSG_NAK: return m->u.nak.tag;
    case ST_MSG_TELEMETRY: return m->u.telemetry.tag;
    case ST_MSG_PARAM_TABLE: return m->u.param_table.tag;
    case ST_MSG_ESTIMATE: return m->u.estimate.tag;
    default: return 0u; /* CentroidFrame and EndOfStream carry no tag */
    }
}

int firmware_handle(firmware_t *fw, const uint8_t *command, size_t n, uint8_t *reply, size_t cap,
                    size_t *reply_len)
{
    st_message_t *const cmd = &fw->command;
    banks_refusal_t refusal;
    uint8_t table[BANKS_TABLE_BYTES];
    uint32_t value = 0u;
    uint32_t crc = 0u;
    int result;
    *reply_len = 0u;
    if (cap < FIRMWARE_REPLY_MAX_BYTES) {
        return FIRMWARE_NO_SPACE;
    }
    if (st_decode(command, n, cmd) != ST_OK) {
        return FIRMWARE_UNDECODABLE;
    }
    switch (cmd->type) {
    case ST_MSG_GET_STATUS:
        return status(fw, cmd->u.get_status.tag, reply, cap, reply_len);
    case ST_MSG_STREAM_CONTROL:
        if (!cmd->u.stream_control.enable) {
            fw->streaming = 0u;
            return ack(cmd->u.stream_control.tag, cmd->type, 0u, reply, cap, reply_len);
        }
        if (!fw->streaming) { /* a new stream: its first exposure is the camera's next one */
            fw->streaming = 1u;
            fw->stream_first_frame = fw->next_frame;
        }
        return ack(cmd->u.stream_control.tag, cmd->type, fw->stream_first_frame, reply, cap, reply_len);
    case ST_MSG_STAGE_BEGIN:
        result = banks_stage_begin(&fw->store, cmd->u.stage_begin.length, &value, &refusal);
        return ack_or_nak(result, cmd->u.stage_begin.tag, cmd->type, value, &refusal, reply, cap, reply_len);
    case ST_MSG_STAGE_CHUNK:
        result = banks_stage_chunk(&fw->store, cmd->u.stage_chunk.offset, cmd->u.stage_chunk.data,
                                   cmd->u.stage_chunk.n_bytes, &refusal);
        return ack_or_nak(result, cmd->u.stage_chunk.tag, cmd->type, 0u, &refusal, reply, cap, reply_len);
    case ST_MSG_STAGE_VERIFY:
        result = banks_stage_verify(&fw->store, cmd->u.stage_verify.crc32, &refusal);
        return ack_or_nak(result, cmd->u.stage_verify.tag, cmd->type, 0u, &refusal, reply, cap, reply_len);
    case ST_MSG_READ_STAGED:
        if (!banks_staged_set(&fw->store, table, &crc)) {
            return nak(cmd->u.read_staged.tag, cmd->type, ST_NAK_NOT_STAGED, "no complete staged set", reply, cap,
                       reply_len);
        }
        return param_table(cmd->u.read_staged.tag, ST_BANK_STAGED, 0u, crc, table, reply, cap, reply_len);
    case ST_MSG_COMMIT:
        result = banks_commit(&fw->store, cmd->u.commit.crc32, cmd->u.commit.nonce, cmd->u.commit.expected_generation,
                              &value, &refusal);
        if (result == BANKS_OK) {
            restart_estimator(fw);
        }
        return ack_or_nak(result, cmd->u.commit.tag, cmd->type, value, &refusal, reply, cap, reply_len);
    case ST_MSG_READ_ACTIVE:
        if (!banks_active_set(&fw->store, &value, table, &crc)) {
            return nak(cmd->u.read_active.tag, cmd->type, ST_NAK_NOT_STAGED, "no parameter set has been committed", reply,
                       cap, reply_len);
        }
        return param_table(cmd->u.read_active.tag, ST_BANK_ACTIVE, value, crc, table, reply, cap, reply_len);
    case ST_MSG_READ_ESTIMATE:
        return read_estimate(fw, cmd->u.read_estimate.tag, reply, cap, reply_len);
    default: {
        pyformat_text_t text;
        pyformat_init(&text);
        pyformat_str(&text, reply_name(cmd->type));
        pyformat_str(&text, " is not a command");
        return nak_text(reply_tag(cmd), cmd->type, ST_NAK_UNKNOWN_COMMAND, &text, reply, cap, reply_len);
    }
    }
}

/* ------------------------------------------------------------------------------------------------ frames */
static void estimate_frame(firmware_t *fw, uint32_t frame, uint32_t n, const uint32_t *star_id, const double *x_px,
                           const double *y_px, const double *r_ref)
{
    double *const r = fw->frame_r_ref;
    uint8_t *const identified = fw->frame_identified;
    uint32_t i;
    uint32_t j;
    if (fw->est == NULL || !fw->est_running || r_ref == NULL || n == 0u || n > ESTIMATOR_SEAM_MAX_STARS) {
        return;
    }
    for (i = 0u; i < n; ++i) {
        uint8_t ok = star_id[i] != 0u ? 1u : 0u;
        for (j = 0u; j < 3u; ++j) {
            ok = (uint8_t)(ok & (isfinite(r_ref[3u * i + j]) ? 1u : 0u));
        }
        identified[i] = ok;
        for (j = 0u; j < 3u; ++j) {
            r[3u * i + j] = ok ? r_ref[3u * i + j] : 0.0;
        }
    }
    if (estimator_seam_update(fw->est, n, x_px, y_px, r, identified) == 0) {
        fw->est_last_frame = frame;
    } else { /* a numerically failed update must not stop the sensor: count it, restart from the active set */
        fw->counters.estimator_faults += 1u;
        restart_estimator(fw);
    }
}

void firmware_set_next_frame(firmware_t *fw, uint32_t frame) { fw->next_frame = frame; }

int firmware_process_frame(firmware_t *fw, uint32_t frame, int64_t t_us, uint32_t n, const uint32_t *star_id,
                           const double *x_px, const double *y_px, const double *r_ref)
{
    uint32_t n_identified = 0u;
    uint32_t i;
    double busy;
    fw->counters.frames_processed += 1u;
    fw->counters.last_frame = frame;
    fw->next_frame = frame + 1u; /* uint32_t: wraps as the Python model's & 0xFFFFFFFF */
    if (fw->has_sensor_time && t_us <= fw->sensor_time_us) {
        t_us = fw->sensor_time_us + (int64_t)nearbyint(fw->budget.min_frame_period_s * 1e6);
    }
    fw->sensor_time_us = t_us;
    fw->has_sensor_time = 1u;
    if (fw->est == NULL || !fw->est_running || r_ref == NULL || n == 0u) {
        return 0;
    }
    if (fw->has_busy_until && t_us < fw->busy_until_us) {
        fw->counters.estimator_skipped += 1u;
        return 0;
    }
    for (i = 0u; i < n; ++i) {
        n_identified += star_id[i] != 0u ? 1u : 0u;
    }
    busy = ceil((double)estimator_seam_cost_flops(&fw->est_config, n_identified) * 1e6 / fw->budget.flops_per_s);
    fw->busy_until_us = t_us + (int64_t)busy;
    fw->has_busy_until = 1u;
    fw->counters.estimator_runs += 1u;
    estimate_frame(fw, frame, n, star_id, x_px, y_px, r_ref);
    return 1;
}
