/* timescale.h: fixed-point time, a translation of the part of onboard/timescale.py the sensor's apparent place
 * uses: an instant as whole days since J2000.0 (int32) plus the day fraction in 2^-32 day (uint32), turned into a
 * float32 difference only (days or Julian centuries since J2000), where float32 is plenty. */
#ifndef ONBOARD_TIMESCALE_H
#define ONBOARD_TIMESCALE_H

#include <stdint.h>

#define TIMESCALE_DAYS_PER_JULIAN_CENTURY 36525.0
#define TIMESCALE_DAYS_PER_JULIAN_YEAR 365.25

/* onboard.timescale.FixedTime (one instant). */
typedef struct {
    int32_t day;   /* whole days since J2000.0 (JD 2451545.0) of the scale */
    uint32_t frac; /* fraction of the day, 2^-32 day */
} timescale_time_t;

/* Days since J2000.0 as float32: day + frac 2^-32 (each converted to float32 first, as the model does). */
float timescale_days_since_j2000(timescale_time_t t);
/* Julian centuries since J2000.0 (the t of the IAU precession and nutation series). */
float timescale_julian_centuries(timescale_time_t t);

#endif
