/* timescale.c: onboard/timescale.py's days_since_j2000 and julian_centuries in float32 (see timescale.h). */
#include "timescale.h"

float timescale_days_since_j2000(timescale_time_t t)
{
    const float frac_to_day = 2.3283064365386962890625e-10f; /* 2^-32, exact */
    return (float)t.day + (float)t.frac * frac_to_day;
}

float timescale_julian_centuries(timescale_time_t t)
{
    return timescale_days_since_j2000(t) / (float)TIMESCALE_DAYS_PER_JULIAN_CENTURY;
}
