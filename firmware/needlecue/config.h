// needlecue estimator firmware: the settings a lab may change, all in this one file (docs/live.md, "The
// firmware"). Rate, oversampling, discarding and baud can also be given on the make command line, e.g.
// `make OVERSAMPLE=1`; the channels and the reference are edited here.
#pragma once

// The channels, in the order they are sent: X(analog pin, name). The number of channels, the banner's
// `channels=` and the ADC multiplexer order all follow from this one list. The names must be the
// model's channel names (a model trained on fsr1..fsr3 refuses a stream of other channels).
#define NC_CHANNELS(X) X(0, "fsr1") X(1, "fsr2") X(2, "fsr3")

#ifndef NC_RATE_HZ
#define NC_RATE_HZ 30  // samples per second, from Timer1: an integer, 4 to 500; the build refuses a rate
                       // whose conversions do not fit half its period (above 320 Hz with 3 channels at 1+4)
#endif
#ifndef NC_OVERSAMPLE
#define NC_OVERSAMPLE 4  // conversions averaged per channel and sample (1 = none); counts stay 10-bit
#endif
#ifndef NC_DISCARD
// Conversions thrown away after each switch of the ADC multiplexer. A force-sensing resistor divider
// is a high-impedance source (tens of kilo-ohms, above the 10 kilo-ohms the ATmega328P datasheet asks
// for): the sample-and-hold capacitor still holds part of the previous channel's voltage.
#define NC_DISCARD 1
#endif
#ifndef NC_BAUD
#define NC_BAUD 115200
#endif
#define NC_VREF "5.0"  // volts at full scale: the Uno's AVCC reference (analogReference DEFAULT)
#define NC_FW "needlecue-fw/1"
