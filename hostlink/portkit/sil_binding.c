/* sil_binding.c: the software-in-the-loop entry points hostlink/portkit/firmware_c.py binds with ctypes. Not part of
 * the firmware core (onboard/c): it only turns the core's structs into plain arguments a foreign-function call can
 * pass. The flash and the random source stay the host's (callbacks), as a platform's HAL would provide them. */
#include <string.h>

#include "firmware.h"

typedef int (*sil_read_fn)(void *ctx, uint32_t address, uint8_t *out, uint32_t n);
typedef int (*sil_erase_fn)(void *ctx, uint32_t sector);
typedef int (*sil_program_fn)(void *ctx, uint32_t address, const uint8_t *data, uint32_t n);
typedef uint32_t (*sil_random_fn)(void *ctx);

size_t sil_firmware_bytes(void) { return sizeof(firmware_t); }

size_t sil_estimator_bytes(void) { return estimator_seam_state_bytes(); }

int sil_estimator_available(void) { return estimator_seam_available(); }

/* Boot a firmware into `fw` (sil_firmware_bytes() bytes). factory_table non-NULL: program it as generation 1 first
 * (onboard.banks.factory_store). Returns 0, 1 for a bad budget, 2 for a power cut. */
int sil_boot(firmware_t *fw, sil_read_fn read, sil_erase_fn erase, sil_program_fn program, sil_random_fn random32,
             const uint8_t *uid, uint32_t has_limits, double design_focal_length_mm, double focal_tolerance,
             double max_distortion_fraction, const char *design_name, uint32_t fixed_point,
             const uint8_t *factory_table, estimator_seam_state_t *est, uint32_t estimate_mask, uint32_t precision,
             double centroid_noise_px, double drift_focal_mm_per_frame, double flops_per_s,
             double min_frame_period_s)
{
    banks_store_t store; /* copied into fw */
    banks_hal_t hal;
    params_limits_t limits;
    estimator_seam_config_t config;
    firmware_budget_t budget;
    int result;
    hal.ctx = NULL;
    hal.read = read;
    hal.erase = erase;
    hal.program = program;
    hal.random32 = random32;
    memcpy(hal.uid, uid, BANKS_UID_BYTES);
    limits = params_default_limits(design_focal_length_mm);
    limits.has_limits = has_limits;
    limits.focal_tolerance = focal_tolerance;
    limits.max_distortion_fraction = max_distortion_fraction;
    limits.design_name = design_name;
    limits.fixed_point = fixed_point;
    result = factory_table != NULL ? banks_factory(&store, &hal, &limits, factory_table)
                                   : banks_boot(&store, &hal, &limits);
    if (result != BANKS_OK) {
        return 2;
    }
    config.estimate_mask = estimate_mask;
    config.precision = precision;
    config.centroid_noise_px = centroid_noise_px;
    config.drift_focal_mm_per_frame = drift_focal_mm_per_frame;
    budget.flops_per_s = flops_per_s;
    budget.min_frame_period_s = min_frame_period_s;
    return firmware_init(fw, &store, est, &config, &budget);
}

int sil_handle(firmware_t *fw, const uint8_t *command, size_t n, uint8_t *reply, size_t cap, size_t *reply_len)
{
    return firmware_handle(fw, command, n, reply, cap, reply_len);
}

int sil_process_frame(firmware_t *fw, uint32_t frame, int64_t t_us, uint32_t n, const uint32_t *star_id,
                      const double *x_px, const double *y_px, const double *r_ref)
{
    return firmware_process_frame(fw, frame, t_us, n, star_id, x_px, y_px, r_ref);
}

void sil_set_next_frame(firmware_t *fw, uint32_t frame) { firmware_set_next_frame(fw, frame); }

/* streaming flag and counters: frames_processed, last_frame, estimator_faults, estimator_runs, estimator_skipped,
 * nonce_counter, stage_state, epoch */
void sil_state(const firmware_t *fw, uint8_t *streaming, uint32_t out[8])
{
    *streaming = fw->streaming;
    out[0] = fw->counters.frames_processed;
    out[1] = fw->counters.last_frame;
    out[2] = fw->counters.estimator_faults;
    out[3] = fw->counters.estimator_runs;
    out[4] = fw->counters.estimator_skipped;
    out[5] = fw->store.nonce_counter;
    out[6] = fw->store.stage_state;
    out[7] = fw->store.epoch;
}

/* the core's own check of a table (params_check_table): 0 usable, else 1 and the text */
int sil_check_table(const uint8_t *table, uint32_t has_limits, double design_focal_length_mm, uint32_t fixed_point,
                    char *text, uint32_t *text_len)
{
    params_limits_t limits = params_default_limits(design_focal_length_mm);
    pyformat_text_t why;
    int bad;
    limits.has_limits = has_limits;
    limits.fixed_point = fixed_point;
    pyformat_init(&why);
    bad = params_check_table(table, &limits, &why);
    memcpy(text, why.buf, why.len);
    *text_len = why.len;
    return bad;
}

/* pyformat.h's formatting of x (kind 0: repr, 1: .3g, 2: .6g, 3: .0f, 4: .0%), for its tests */
uint32_t sil_format(uint32_t kind, double x, char *text)
{
    pyformat_text_t t;
    pyformat_init(&t);
    switch (kind) {
    case 0: pyformat_repr(&t, x); break;
    case 1: pyformat_g(&t, x, 3u); break;
    case 2: pyformat_g(&t, x, 6u); break;
    case 3: pyformat_f0(&t, x); break;
    default: pyformat_percent0(&t, x); break;
    }
    memcpy(text, t.buf, t.len);
    return t.len;
}
